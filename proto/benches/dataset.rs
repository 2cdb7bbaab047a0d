//! Dataset writer throughput and size on disk at K = 10, chunks of 64 transitions (the runtime's
//! default batch), on transitions shaped like the default world's: coordinates below 10, AoI
//! values up to 100, one episode of T = 100 steps after another.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion, Throughput};
use uavmeta_proto::dataset::{DatasetHeader, DatasetReader, DatasetWriter, Transition};

const K: u16 = 10;
const TRANSITIONS: u64 = 10_000;
const CHUNK: usize = 64;

fn header() -> DatasetHeader {
    DatasetHeader {
        devices: K,
        task: 0,
        task_name: "lambda-300".into(),
        world_hash: 0,
    }
}

fn world_like(i: u64) -> Transition {
    let obs = |t: u64| -> Vec<u16> {
        let mut o = vec![(t % 10) as u16, (t / 10 % 10) as u16];
        o.extend((0..K as u64).map(|k| ((t + 3 * k) % 100 + 1) as u16));
        o
    };
    Transition {
        task: 0,
        actor: 0,
        episode: i / 100,
        step: (i % 100) as u32,
        seq: i,
        obs: obs(i),
        action: (i * 7 % (5 * K as u64)) as u16,
        reward: -55.5 - (i % 13) as f32,
        next_obs: obs(i + 1),
        truncated: i % 100 == 99,
    }
}

fn bench(c: &mut Criterion) {
    let data: Vec<Transition> = (0..TRANSITIONS).map(world_like).collect();
    let dir = tempfile::tempdir().expect("a temporary directory");

    // Size on disk: the header is written once, so report the per-transition cost of a large file.
    let sized = dir.path().join("sized.uavds");
    let mut writer = DatasetWriter::create(&sized, header()).expect("create");
    for chunk in data.chunks(CHUNK) {
        writer.append(chunk).expect("append");
    }
    writer.sync().expect("sync");
    let bytes = std::fs::metadata(&sized).expect("metadata").len();
    eprintln!(
        "dataset file: {TRANSITIONS} transitions at K = {K} in chunks of {CHUNK}: {bytes} bytes, {:.1} bytes per transition",
        bytes as f64 / TRANSITIONS as f64
    );

    let mut group = c.benchmark_group("dataset");
    group.throughput(Throughput::Elements(TRANSITIONS));
    let path = dir.path().join("bench.uavds");
    // The file's creation (a header and an fsync) is timed on its own below, not in the appends.
    let create = || DatasetWriter::create(&path, header()).expect("create");
    group.bench_function("append_10k_in_chunks_of_64", |b| {
        b.iter_batched(
            create,
            |mut writer| {
                for chunk in data.chunks(CHUNK) {
                    writer.append(chunk).expect("append");
                }
                writer.flush().expect("flush");
            },
            BatchSize::PerIteration,
        )
    });
    group.bench_function("append_10k_in_chunks_of_64_then_sync", |b| {
        b.iter_batched(
            create,
            |mut writer| {
                for chunk in data.chunks(CHUNK) {
                    writer.append(chunk).expect("append");
                }
                writer.sync().expect("sync");
            },
            BatchSize::PerIteration,
        )
    });
    group.throughput(Throughput::Elements(1));
    group.bench_function("create_file", |b| b.iter(create));
    group.throughput(Throughput::Elements(TRANSITIONS));
    group.bench_function("read_10k", |b| {
        b.iter_batched(
            || (),
            |()| DatasetReader::open(&sized).expect("read"),
            BatchSize::SmallInput,
        )
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
