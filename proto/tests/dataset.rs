//! The dataset format: round trips, crash recovery, corruption reports and determinism.

use std::fs::OpenOptions;
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;

use proptest::prelude::*;
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::{
    sample_shots, split, DatasetError, DatasetHeader, DatasetReader, DatasetWriter, Transition,
    SCHEMA_VERSION,
};

const K: u16 = 10;

fn header() -> DatasetHeader {
    DatasetHeader {
        devices: K,
        task: 3,
        task_name: "lambda-400".into(),
        world_hash: 0x1234_5678_9abc_def0,
    }
}

/// A transition whose every field depends on `i`, so mix-ups between transitions show.
fn transition(i: u64) -> Transition {
    let obs: Vec<u16> = (0..2 + K as u64)
        .map(|j| ((i * 7 + j * 13) % 101) as u16)
        .collect();
    let next_obs: Vec<u16> = obs.iter().map(|v| (v + 1) % 101).collect();
    Transition {
        task: 3,
        actor: (i % 4) as u32,
        episode: i / 100,
        step: (i % 100) as u32,
        seq: i,
        obs,
        action: (i % (5 * K as u64)) as u16,
        reward: -(i as f32) * 0.25,
        next_obs,
        truncated: i % 100 == 99,
    }
}

fn transitions(range: std::ops::Range<u64>) -> Vec<Transition> {
    range.map(transition).collect()
}

/// Writes `chunks` chunks of `per_chunk` transitions; returns the byte offset where each chunk starts.
fn write_chunks(path: &Path, chunks: u64, per_chunk: u64) -> Vec<u64> {
    let mut writer = DatasetWriter::create(path, header()).unwrap();
    let mut starts = Vec::new();
    for c in 0..chunks {
        starts.push(writer.len_bytes());
        writer
            .append(&transitions(c * per_chunk..(c + 1) * per_chunk))
            .unwrap();
    }
    writer.sync().unwrap();
    starts
}

fn overwrite(path: &Path, offset: u64, bytes: &[u8]) {
    let mut file = OpenOptions::new().write(true).open(path).unwrap();
    file.seek(SeekFrom::Start(offset)).unwrap();
    file.write_all(bytes).unwrap();
}

fn flip_byte(path: &Path, offset: u64) {
    let bytes = std::fs::read(path).unwrap();
    overwrite(path, offset, &[bytes[offset as usize] ^ 0x5a]);
}

#[test]
fn round_trip_keeps_header_and_transitions_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    write_chunks(&path, 3, 40);
    let reader = DatasetReader::open(&path).unwrap();
    assert_eq!(reader.header(), &header());
    assert_eq!(reader.transitions(), transitions(0..120).as_slice());
}

#[test]
fn open_append_continues_a_file_without_recovery() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    write_chunks(&path, 2, 10);
    let (mut writer, recovery) = DatasetWriter::open_append(&path).unwrap();
    assert_eq!(recovery, None);
    assert_eq!(writer.transitions(), 20);
    writer.append(&transitions(20..25)).unwrap();
    writer.sync().unwrap();
    assert_eq!(
        DatasetReader::open(&path).unwrap().transitions(),
        transitions(0..25).as_slice()
    );
}

#[test]
fn torn_tail_is_cut_by_the_writer_and_rejected_by_the_reader() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let starts = write_chunks(&path, 3, 30);
    let full_len = std::fs::metadata(&path).unwrap().len();
    // A crash in the middle of writing the third chunk.
    let torn_at = starts[2] + (full_len - starts[2]) / 2;
    OpenOptions::new()
        .write(true)
        .open(&path)
        .unwrap()
        .set_len(torn_at)
        .unwrap();

    match DatasetReader::open(&path) {
        Err(DatasetError::Corrupt {
            path: p,
            offset,
            reason,
        }) => {
            assert_eq!(p, path);
            assert_eq!(offset, starts[2]);
            assert!(reason.contains("cut short"), "{reason}");
        }
        other => panic!("expected a corrupt-chunk error, got {other:?}"),
    }

    let (mut writer, recovery) = DatasetWriter::open_append(&path).unwrap();
    let recovery = recovery.expect("the torn chunk is reported");
    assert_eq!(recovery.kept_transitions, 60);
    assert_eq!(recovery.offset, starts[2]);
    assert_eq!(recovery.cut_bytes, torn_at - starts[2]);
    assert_eq!(std::fs::metadata(&path).unwrap().len(), starts[2]);
    assert_eq!(
        DatasetReader::open(&path).unwrap().transitions(),
        transitions(0..60).as_slice()
    );

    // Appending after the cut gives a file the strict reader accepts.
    writer.append(&transitions(60..70)).unwrap();
    writer.sync().unwrap();
    assert_eq!(
        DatasetReader::open(&path).unwrap().transitions(),
        transitions(0..70).as_slice()
    );
}

#[test]
fn corrupt_last_chunk_is_cut_and_a_torn_chunk_header_too() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let starts = write_chunks(&path, 2, 10);
    let full_len = std::fs::metadata(&path).unwrap().len();
    flip_byte(&path, starts[1] + 30);
    let (_, recovery) = DatasetWriter::open_append(&path).unwrap();
    let recovery = recovery.unwrap();
    assert_eq!(
        (
            recovery.kept_transitions,
            recovery.offset,
            recovery.cut_bytes
        ),
        (10, starts[1], full_len - starts[1])
    );
    assert!(recovery.reason.contains("CRC32"), "{}", recovery.reason);

    // Only a few bytes of a chunk header made it to disk.
    let mut file = OpenOptions::new().append(true).open(&path).unwrap();
    file.write_all(b"UMC").unwrap();
    let (_, recovery) = DatasetWriter::open_append(&path).unwrap();
    assert_eq!(recovery.unwrap().cut_bytes, 3);
    assert_eq!(DatasetReader::open(&path).unwrap().transitions().len(), 10);
}

#[test]
fn flipped_byte_in_the_middle_chunk_names_file_and_offset_and_is_not_cut() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let starts = write_chunks(&path, 3, 20);
    let before = std::fs::read(&path).unwrap();
    flip_byte(&path, starts[1] + 25);

    let error = DatasetReader::open(&path).unwrap_err();
    let message = error.to_string();
    assert!(message.contains(&path.display().to_string()), "{message}");
    assert!(
        message.contains(&format!("offset {}", starts[1])),
        "{message}"
    );
    assert!(matches!(error, DatasetError::Corrupt { offset, .. } if offset == starts[1]));

    // The writer must not throw the good third chunk away.
    let error = DatasetWriter::open_append(&path)
        .err()
        .expect("damage in the middle is an error");
    assert!(matches!(error, DatasetError::Corrupt { offset, .. } if offset == starts[1]));
    assert_eq!(std::fs::read(&path).unwrap().len(), before.len());
}

#[test]
fn damaged_length_field_in_the_middle_is_not_mistaken_for_a_tail() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let starts = write_chunks(&path, 3, 20);
    // The payload length of the middle chunk now points far past the end of the file.
    overwrite(&path, starts[1] + 16, &u32::MAX.to_le_bytes());
    assert!(DatasetWriter::open_append(&path).is_err());
}

#[test]
fn same_data_gives_byte_identical_files() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    write_chunks(&a, 4, 25);
    write_chunks(&b, 4, 25);
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
}

#[test]
fn wrong_magic_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("config.toml");
    std::fs::write(&path, "[world]\ndevices = 10\n").unwrap();
    let message = DatasetReader::open(&path).unwrap_err().to_string();
    assert!(
        message.contains("not a uavmeta dataset") && message.contains("config.toml"),
        "{message}"
    );
    assert!(matches!(
        DatasetWriter::open_append(&path),
        Err(DatasetError::BadMagic { .. })
    ));
}

#[test]
fn other_schema_version_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    write_chunks(&path, 1, 5);
    overwrite(&path, 8, &(SCHEMA_VERSION + 1).to_le_bytes());
    let error = DatasetReader::open(&path).unwrap_err();
    assert!(
        matches!(error, DatasetError::SchemaVersion { found, offset: 8, .. } if found == SCHEMA_VERSION + 1),
        "{error}"
    );
    assert!(error
        .to_string()
        .contains(&format!("this build reads version {SCHEMA_VERSION}")));
}

#[test]
fn observation_length_mismatch_is_refused_on_write() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let mut writer = DatasetWriter::create(&path, header()).unwrap();
    let mut bad = transitions(0..3);
    bad[2].next_obs.pop();
    match writer.append(&bad) {
        Err(DatasetError::ObservationLength {
            index,
            field,
            found,
            expected,
            ..
        }) => {
            assert_eq!((index, field, found, expected), (2, "next_obs", 11, 12));
        }
        other => panic!("expected an observation-length error, got {other:?}"),
    }
    writer.sync().unwrap();
    assert!(DatasetReader::open(&path).unwrap().transitions().is_empty());
}

/// A chunk built by hand from the module doc's layout, bypassing the writer's checks.
fn raw_chunk(devices: u16, task: u32, transitions: &[Transition]) -> Vec<u8> {
    // The learner host's (empty) host tag.
    let mut payload = vec![0u8];
    for t in transitions {
        payload.extend(postcard::to_stdvec(t).unwrap());
    }
    let mut chunk = b"UMCH".to_vec();
    chunk.extend(SCHEMA_VERSION.to_le_bytes());
    chunk.extend(devices.to_le_bytes());
    chunk.extend(task.to_le_bytes());
    chunk.extend((transitions.len() as u32).to_le_bytes());
    chunk.extend((payload.len() as u32).to_le_bytes());
    chunk.extend(payload);
    chunk.extend(crc32fast::hash(&chunk).to_le_bytes());
    chunk
}

#[test]
fn observation_length_mismatch_is_refused_on_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let starts = write_chunks(&path, 2, 5);
    let end = std::fs::metadata(&path).unwrap().len();
    let mut short = transitions(10..12);
    short[1].obs.truncate(2);
    let mut file = OpenOptions::new().append(true).open(&path).unwrap();
    file.write_all(&raw_chunk(K, 3, &short)).unwrap();
    match DatasetReader::open(&path) {
        Err(DatasetError::ObservationLength {
            offset,
            index,
            field,
            found,
            expected,
            ..
        }) => {
            assert_eq!(
                (offset, index, field, found, expected),
                (end, 1, "obs", 2, 12)
            );
        }
        other => panic!("expected an observation-length error, got {other:?}"),
    }

    // A well-formed chunk of another K is refused as well.
    OpenOptions::new()
        .write(true)
        .open(&path)
        .unwrap()
        .set_len(starts[1])
        .unwrap();
    let mut file = OpenOptions::new().append(true).open(&path).unwrap();
    file.write_all(&raw_chunk(K - 1, 3, &[])).unwrap();
    let message = DatasetReader::open(&path).unwrap_err().to_string();
    assert!(
        message.contains("K = 9") && message.contains("K = 10"),
        "{message}"
    );
}

#[test]
fn invalid_action_task_or_reward_is_refused_on_write() {
    let dir = tempfile::tempdir().unwrap();
    let mut writer = DatasetWriter::create(dir.path().join("d"), header()).unwrap();
    let mut bad = transition(0);
    bad.action = 5 * K;
    assert!(matches!(
        writer.append(&[bad]),
        Err(DatasetError::InvalidTransition { .. })
    ));
    let mut bad = transition(0);
    bad.task = 4;
    assert!(matches!(
        writer.append(&[bad]),
        Err(DatasetError::InvalidTransition { .. })
    ));
    let mut bad = transition(0);
    bad.reward = f32::NAN;
    assert!(matches!(
        writer.append(&[bad]),
        Err(DatasetError::InvalidTransition { .. })
    ));
    assert_eq!(writer.transitions(), 0);
}

#[test]
fn header_for_a_config_task_and_world_check() {
    let config = Config::default();
    let header = DatasetHeader::for_task(&config, "lambda-300").unwrap();
    assert_eq!(
        (header.devices, header.task, header.world_hash),
        (10, 8, config.world_hash())
    );
    assert!(DatasetHeader::for_task(&config, "lambda-301").is_err());

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    DatasetWriter::create(&path, header.clone()).unwrap();
    let reader = DatasetReader::open(&path).unwrap();
    reader.check_world(&config).unwrap();
    let other = Config::from_toml_str("[world]\nlayout_seed = 7", "other.toml", &[]).unwrap();
    let message = reader.check_world(&other).unwrap_err().to_string();
    assert!(
        message.contains("other.toml") && message.contains("world hash"),
        "{message}"
    );

    let (_, recovery) = DatasetWriter::open_or_create(&path, header.clone()).unwrap();
    assert_eq!(recovery, None);
    let other_task = DatasetHeader::for_task(&config, "lambda-0").unwrap();
    assert!(matches!(
        DatasetWriter::open_or_create(&path, other_task),
        Err(DatasetError::HeaderMismatch { .. })
    ));
}

#[test]
fn split_is_seeded_disjoint_and_complete() {
    let data = transitions(0..101);
    let (support, query) = split(&data, 0.3, 9).unwrap();
    assert_eq!((support.len(), query.len()), (30, 71));
    let mut seqs: Vec<u64> = support.iter().chain(&query).map(|t| t.seq).collect();
    seqs.sort_unstable();
    assert_eq!(seqs, (0..101).collect::<Vec<_>>());
    assert!(
        support.windows(2).all(|w| w[0].seq < w[1].seq),
        "support keeps file order"
    );
    assert_eq!(split(&data, 0.3, 9).unwrap(), (support.clone(), query));
    assert_ne!(
        split(&data, 0.3, 10).unwrap().0,
        support,
        "another seed draws another support set"
    );
    // Both sets get at least one transition.
    assert_eq!(split(&data[..2], 0.01, 0).unwrap().0.len(), 1);
    assert!(matches!(
        split(&data, 1.0, 0),
        Err(DatasetError::BadSplit { .. })
    ));
    assert!(matches!(
        split(&data[..1], 0.5, 0),
        Err(DatasetError::BadSplit { .. })
    ));
}

#[test]
fn shots_are_distinct_seeded_and_bounded() {
    let data = transitions(0..50);
    let shots = sample_shots(&data, 20, 4).unwrap();
    let mut seqs: Vec<u64> = shots.iter().map(|t| t.seq).collect();
    seqs.sort_unstable();
    seqs.dedup();
    assert_eq!(seqs.len(), 20);
    assert_eq!(sample_shots(&data, 20, 4).unwrap(), shots);
    assert_ne!(sample_shots(&data, 20, 5).unwrap(), shots);
    assert_eq!(sample_shots(&data, 50, 4).unwrap().len(), 50);
    let message = sample_shots(&data, 51, 4).unwrap_err().to_string();
    assert!(
        message.contains("51") && message.contains("50 available"),
        "{message}"
    );
    assert!(sample_shots(&data, 0, 4).is_err());
}

fn arb_transition() -> impl Strategy<Value = Transition> {
    let obs = || proptest::collection::vec(any::<u16>(), 2 + K as usize);
    (
        any::<u32>(),
        any::<u64>(),
        any::<u32>(),
        any::<u64>(),
        obs(),
        0..5 * K,
        -1e6f32..1e6,
        obs(),
        any::<bool>(),
    )
        .prop_map(
            |(actor, episode, step, seq, obs, action, reward, next_obs, truncated)| Transition {
                task: 3,
                actor,
                episode,
                step,
                seq,
                obs,
                action,
                reward,
                next_obs,
                truncated,
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn any_transitions_in_any_chunks_round_trip(
        data in proptest::collection::vec(arb_transition(), 0..60),
        cuts in proptest::collection::vec(0usize..60, 0..5),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.uavds");
        let mut bounds: Vec<usize> = cuts.into_iter().map(|c| c.min(data.len())).collect();
        bounds.push(0);
        bounds.push(data.len());
        bounds.sort_unstable();
        let mut writer = DatasetWriter::create(&path, header()).unwrap();
        for w in bounds.windows(2) {
            writer.append(&data[w[0]..w[1]]).unwrap();
        }
        writer.sync().unwrap();
        let reader = DatasetReader::open(&path).unwrap();
        prop_assert_eq!(reader.transitions(), data.as_slice());
    }
}

#[test]
fn every_chunk_records_the_host_that_made_it_and_the_reader_counts_them() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.uavds");
    let mut writer = DatasetWriter::create(&path, header()).unwrap();
    writer.append(&transitions(0..3)).unwrap();
    writer.append_from("actors-1", &transitions(3..5)).unwrap();
    writer.sync().unwrap();
    let (mut writer, recovery) = DatasetWriter::open_append(&path).unwrap();
    assert!(recovery.is_none());
    writer.append_from("actors-1", &transitions(5..6)).unwrap();
    writer.sync().unwrap();
    let reader = DatasetReader::open(&path).unwrap();
    let counts: Vec<(&str, u64)> = reader.provenance().into_iter().collect();
    assert_eq!(counts, [("", 3), ("actors-1", 3)]);
    let hosts: Vec<&str> = reader.with_hosts().map(|(host, _)| host).collect();
    assert_eq!(hosts, ["", "", "", "actors-1", "actors-1", "actors-1"]);
    let long = "h".repeat(256);
    assert!(writer.append_from(&long, &transitions(6..7)).is_err());
}
