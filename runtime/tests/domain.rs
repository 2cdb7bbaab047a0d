//! Start-up in an iceoryx2 domain that a killed process left behind, with real shared memory.

use std::fs::File;
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

use uavmeta_proto::config::RunConfig;
use uavmeta_runtime::{domain, run_dir};

/// A domain of this test's own, removed when dropped.
struct Domain(RunConfig);

impl Domain {
    fn new(name: &str) -> Self {
        let domain = format!("{name}{}", std::process::id());
        Domain(RunConfig {
            domain,
            ..RunConfig::default()
        })
    }

    /// A segment at size zero in the domain, as a process killed between `shm_open` and
    /// `ftruncate` leaves it, last modified `age` ago.
    fn zero_sized_segment(&self, name: &str, age: Duration) -> PathBuf {
        let path = PathBuf::from(format!("/dev/shm/iox2_{}_{name}", self.0.domain));
        let file = File::create(&path).expect("create the segment");
        file.set_modified(SystemTime::now() - age)
            .expect("age the segment");
        path
    }
}

impl Drop for Domain {
    fn drop(&mut self) {
        let _ = domain::remove_domain(&self.0);
    }
}

#[test]
fn a_young_unfinished_segment_is_waited_for_until_it_is_old_enough_to_remove() {
    let domain = Domain::new("unfinishedold");
    let segment = domain.zero_sized_segment("killed", Duration::from_secs(8));
    let start = Instant::now();
    let node = domain::node("starting", &domain.0).expect("a node despite the leftover");
    assert!(!segment.exists(), "the leftover segment is still there");
    assert!(
        start.elapsed() >= Duration::from_secs(1),
        "removed after {:?}, before it was 10 s old: it could have been a creation in progress",
        start.elapsed()
    );
    drop(node);
}

#[test]
fn a_segment_sized_while_waited_for_is_a_finished_creation_and_kept() {
    let domain = Domain::new("unfinishedsized");
    let segment = domain.zero_sized_segment("creating", Duration::ZERO);
    let sizing = {
        let segment = segment.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(300));
            File::options()
                .write(true)
                .open(&segment)
                .and_then(|f| f.set_len(4096))
                .expect("size the segment");
        })
    };
    let node = domain::node("starting", &domain.0).expect("a node");
    sizing.join().expect("the sizing thread");
    assert!(segment.exists(), "a segment being created was removed");
    assert_eq!(std::fs::metadata(&segment).expect("stat").len(), 4096);
    drop(node);
    std::fs::remove_file(&segment).expect("remove the test's segment");
}

/// Another user's process redoing `touch` on the file at `path` every 20 ms until stopped, as
/// iceoryx2's files are world-writable: a leftover kept so never gets old enough to remove, and
/// must not be waited for ever.
fn again_and_again(
    path: PathBuf,
    touch: fn(&File),
) -> (
    std::sync::Arc<std::sync::atomic::AtomicBool>,
    std::thread::JoinHandle<()>,
) {
    use std::sync::atomic::{AtomicBool, Ordering};
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let handle = std::thread::spawn(move || {
        while !flag.load(Ordering::Relaxed) {
            if let Ok(file) = File::options().write(true).open(&path) {
                touch(&file);
                let _ = file.set_modified(SystemTime::now());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    });
    (stop, handle)
}

#[test]
fn a_segment_truncated_again_and_again_is_given_up_on_and_the_cleaner_never_blocks_its_caller() {
    use std::sync::atomic::Ordering;
    let domain = Domain::new("truncated");
    let segment = domain.zero_sized_segment("hostile", Duration::ZERO);
    let (stop, truncating) = again_and_again(segment.clone(), |file| {
        let _ = file.set_len(0);
    });
    // Node creation sweeps: it gives up on the segment instead of waiting for it to age.
    let node = domain::node("starting", &domain.0).expect("a node despite the truncation");
    assert!(segment.exists(), "a young segment was removed");
    // The cleaner's sweeps run on its thread: a request returns at once, and each sweep ends.
    let cleaner = domain::Cleaner::start("truncated", &domain.0);
    let first = cleaner.request();
    assert!(
        !cleaner.finished(first + 1),
        "a ticket not yet asked for is not finished"
    );
    let start = Instant::now();
    while !cleaner.finished(first) {
        assert!(
            start.elapsed() < Duration::from_secs(180),
            "the sweep never ended"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    stop.store(true, Ordering::Relaxed);
    truncating.join().expect("the truncating thread");
    drop((cleaner, node));
    std::fs::remove_file(&segment).expect("remove the test's segment");
}

#[test]
fn a_failed_atomic_write_leaves_no_temporary_file() {
    let dir = tempfile::tempdir().expect("tmp");
    // Renaming a file onto a non-empty directory fails, as a write to a full disk does.
    let target = dir.path().join("targets.json");
    std::fs::create_dir(&target).expect("dir");
    std::fs::write(target.join("x"), b"x").expect("file");
    let error = run_dir::write_atomic(&target, b"{}").expect_err("cannot replace a directory");
    assert!(error.to_string().contains("targets.json"), "{error}");
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .expect("list")
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert_eq!(
        left,
        vec![std::ffi::OsString::from("targets.json")],
        "a temporary file was left"
    );
}

/// The static config file of a service, in the domain's services directory, as iceoryx2 names it:
/// found by creating the service once (and dropping it, which removes the file again).
fn service_file(domain: &Domain, service: &str) -> PathBuf {
    use iceoryx2::prelude::*;
    let config = domain::iceoryx_config(&domain.0).expect("the domain's config");
    let dir = PathBuf::from(config.global.service_dir().to_string());
    let node = domain::node("probe", &domain.0).expect("a node");
    let name: ServiceName = service.try_into().expect("a service name");
    let created = node
        .service_builder(&name)
        .publish_subscribe::<u64>()
        .open_or_create()
        .expect("the service");
    let files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("the services directory")
        .flatten()
        .map(|e| e.path())
        .collect();
    drop((created, node));
    assert_eq!(
        files.len(),
        1,
        "one service, one static config file: {files:?}"
    );
    files[0].clone()
}

/// What a process killed while creating a service leaves: its static config file empty and still
/// writable (iceoryx2 makes it read-only once written). iceoryx2 0.10 takes that for a creation in
/// progress for ever, so every later open fails with `HangsInCreation`; a store killed at that
/// moment could never be restarted, and one restarted a moment later failed once (the chaos
/// test). Starting a node waits until the file is older than any creation takes, removes it, and
/// the service opens again.
#[test]
fn a_service_left_half_created_by_a_killed_process_a_moment_ago_opens_again() {
    use iceoryx2::prelude::*;
    use std::os::unix::fs::PermissionsExt;
    let domain = Domain::new("halfcreated");
    let service = "uavmeta/test/acks";
    let file = service_file(&domain, service);
    assert!(!file.exists(), "dropping the service keeps its file");
    let leftover = File::create(&file).expect("the leftover file");
    leftover
        .set_permissions(std::fs::Permissions::from_mode(0o600))
        .expect("writable, as during creation");
    leftover
        .set_modified(SystemTime::now() - Duration::from_secs(8))
        .expect("age the leftover");
    drop(leftover);

    let open = |node: &Node<ipc::Service>| {
        let name: ServiceName = service.try_into().expect("a service name");
        node.service_builder(&name)
            .publish_subscribe::<u64>()
            .open_or_create()
            .map(drop)
    };
    // The leftover is as the killed store's was: the service cannot be opened.
    let config = domain::iceoryx_config(&domain.0).expect("the domain's config");
    let plain = NodeBuilder::new()
        .config(&config)
        .create::<ipc::Service>()
        .expect("a node that sweeps nothing");
    let error = open(&plain).expect_err("a half-created service opens");
    assert!(
        format!("{error:?}").contains("HangsInCreation"),
        "{error:?}"
    );
    drop(plain);

    let start = Instant::now();
    let node = domain::node("restarted", &domain.0).expect("a node");
    assert!(!file.exists(), "the leftover is still there");
    assert!(
        start.elapsed() >= Duration::from_secs(1),
        "removed after {:?}, before it was 10 s old: it could have been a creation in progress",
        start.elapsed()
    );
    open(&node).expect("the service opens again");
}

#[test]
fn a_service_file_kept_unfinished_again_and_again_is_given_up_on() {
    use std::os::unix::fs::PermissionsExt;
    use std::sync::atomic::Ordering;
    let domain = Domain::new("keptunfinished");
    let file = service_file(&domain, "uavmeta/test/hostile");
    File::create(&file)
        .and_then(|f| f.set_permissions(std::fs::Permissions::from_mode(0o600)))
        .expect("a writable service file, as during creation");
    let (stop, refreshing) = again_and_again(file.clone(), |_| {});
    // Node creation sweeps: it gives up on the file at its bound instead of waiting for ever.
    let node = domain::node("starting", &domain.0).expect("a node despite the hostile file");
    assert!(
        file.exists(),
        "a service file modified a moment ago was removed"
    );
    stop.store(true, Ordering::Relaxed);
    refreshing.join().expect("the refreshing thread");
    drop(node);
    std::fs::remove_file(&file).expect("remove the test's service file");
}
