//! Pinned numerics (learner/src/numerics.rs): a dataset and a checkpoint made with the same
//! config and seed are the same bytes whichever instruction sets MKL and ATen may use and whichever
//! vendor MKL believes made the CPU, and the binary's pin reaches MKL before its first call.

use std::path::Path;
use std::process::{Command, Output};

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/default.toml");

/// Small but real: an online DQN agent trains and its buffer is sampled, CQL trains on it.
const SMALL: &[&str] = &[
    "world.horizon=30",
    "learner.hidden=[64,64]",
    "collect.transitions=200",
    "collect.dqn.steps=800",
    "collect.dqn.replay_capacity=800",
    "collect.dqn.learning_starts=200",
    "collect.dqn.eps_decay_steps=400",
];

/// `uavmeta SUBCOMMAND` in `dir` with the environment `env` added.
fn uavmeta(dir: &Path, env: &[(&str, &str)], subcommand: &str, args: &[&str]) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_uavmeta"));
    command
        .current_dir(dir)
        .args([subcommand, "--config", CONFIG, "--task", "lambda-300"]);
    for set in SMALL {
        command.args(["--set", set]);
    }
    // The test's own environment must not decide what it tests.
    for name in [
        "UAVMETA_NUMERICS",
        "MKL_CBWR",
        "ATEN_CPU_CAPABILITY",
        "MKL_ENABLE_INSTRUCTIONS",
        "ONEDNN_MAX_CPU_ISA",
        "MKL_VERBOSE",
        "LD_PRELOAD",
    ] {
        command.env_remove(name);
    }
    let output = command
        .envs(env.iter().copied())
        .args(args)
        .output()
        .expect("run uavmeta");
    assert!(
        output.status.success(),
        "uavmeta {subcommand} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// Collects a dataset and trains CQL on it under `env`; returns the two files' bytes.
fn dataset_and_checkpoint(env: &[(&str, &str)]) -> (Vec<u8>, Vec<u8>) {
    let dir = tempfile::tempdir().expect("temp dir");
    uavmeta(dir.path(), env, "collect", &["--out", "d.uavds"]);
    let train = [
        "--algo",
        "cql",
        "--dataset",
        "d.uavds",
        "--shots",
        "200",
        "--epochs",
        "3",
        "--out",
        "t",
    ];
    uavmeta(dir.path(), env, "train", &train);
    let read = |p: &str| std::fs::read(dir.path().join(p)).expect(p);
    (read("d.uavds"), read("t/final.safetensors"))
}

/// In each pinned mode, the machine's best instruction sets and an AVX2-only MKL and ATen (what a
/// CPU without AVX-512 runs) give the same dataset and checkpoint bytes, as `cmp` would see them.
#[test]
fn pinned_results_do_not_depend_on_the_instruction_set() {
    for mode in ["avx2", "compatible"] {
        let best = dataset_and_checkpoint(&[("UAVMETA_NUMERICS", mode)]);
        let avx2_only = dataset_and_checkpoint(&[
            ("UAVMETA_NUMERICS", mode),
            ("MKL_ENABLE_INSTRUCTIONS", "AVX2"),
        ]);
        assert!(best.0 == avx2_only.0, "{mode}: the datasets differ");
        assert!(best.1 == avx2_only.1, "{mode}: the checkpoints differ");
    }
}

/// The pin is set inside the binary, before libtorch's first MKL call: MKL reports the
/// reproducible mode of each setting in its verbose log, and nothing without the pin.
#[test]
fn the_pin_reaches_mkl() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut modes = Vec::new();
    for mode in ["avx2", "compatible", "native"] {
        let env = [("UAVMETA_NUMERICS", mode), ("MKL_VERBOSE", "1")];
        let out = uavmeta(
            dir.path(),
            &env,
            "collect",
            &["--out", &format!("{mode}.uavds")],
        );
        let log = String::from_utf8_lossy(&out.stdout).to_string()
            + &String::from_utf8_lossy(&out.stderr);
        let cnr = log
            .split_whitespace()
            .find(|w| w.starts_with("CNR:"))
            .unwrap_or_else(|| panic!("{mode}: MKL logged no call:\n{log}"))
            .to_string();
        modes.push(cnr);
    }
    assert!(modes[0].ends_with(",STRICT"), "avx2: {}", modes[0]);
    assert_eq!(modes[1], "CNR:COMPATIBLE,STRICT");
    assert_eq!(modes[2], "CNR:OFF");
}

/// A shared library that answers MKL's vendor question "no", as MKL's own check does on an AMD
/// CPU, and says on stderr that it was loaded; built with the C compiler the build already needs.
fn not_intel_library(dir: &Path) -> std::path::PathBuf {
    let source = dir.join("not_intel.c");
    let library = dir.join("not_intel.so");
    std::fs::write(
        &source,
        "#include <stdio.h>\n\
         int mkl_serv_intel_cpu_true(void) { return 0; }\n\
         __attribute__((constructor)) static void loaded(void) { fputs(\"not_intel.so loaded\\n\", stderr); }\n",
    )
    .expect("write not_intel.c");
    let compiler = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let status = Command::new(&compiler)
        .args(["-shared", "-fPIC", "-o"])
        .arg(&library)
        .arg(&source)
        .status()
        .unwrap_or_else(|e| panic!("run {compiler}: {e}"));
    assert!(status.success(), "{compiler} could not build not_intel.so");
    library
}

/// The default pin holds on any vendor's CPU: with MKL told it is not on an Intel CPU (what made
/// an AMD EPYC run MKL's own dispatch instead of the AVX2 branch, and other learned numbers), MKL
/// still runs the AVX2 branch and the dataset and checkpoint are the same bytes. Fails when the
/// executable does not answer MKL's question itself (learner/src/numerics.rs, build/rpath.rs).
#[test]
fn the_pinned_branch_does_not_depend_on_the_cpu_vendor() {
    let dir = tempfile::tempdir().expect("temp dir");
    let library = not_intel_library(dir.path());
    let preload = library.to_str().expect("utf-8 temp path");
    let out = uavmeta(
        dir.path(),
        &[("LD_PRELOAD", preload), ("MKL_VERBOSE", "1")],
        "collect",
        &["--out", "d.uavds"],
    );
    let log =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(
        log.contains("not_intel.so loaded"),
        "the library was not preloaded:\n{log}"
    );
    let mut cnr: Vec<&str> = log
        .split_whitespace()
        .filter(|w| w.starts_with("CNR:"))
        .collect();
    cnr.sort_unstable();
    cnr.dedup();
    assert!(!cnr.is_empty(), "MKL logged no call:\n{log}");
    assert_eq!(cnr, ["CNR:AVX2,STRICT"], "the branches MKL ran");

    let intel = dataset_and_checkpoint(&[]);
    let not_intel = dataset_and_checkpoint(&[("LD_PRELOAD", preload)]);
    assert!(intel.0 == not_intel.0, "the datasets differ");
    assert!(intel.1 == not_intel.1, "the checkpoints differ");
}

/// An unknown mode is refused, naming the variable, the value and the modes there are.
#[test]
fn an_unknown_mode_is_refused() {
    let output = Command::new(env!("CARGO_BIN_EXE_uavmeta"))
        .args([
            "env",
            "rollout",
            "--config",
            CONFIG,
            "--task",
            "lambda-300",
            "--episodes",
            "1",
        ])
        .env("UAVMETA_NUMERICS", "fast")
        .output()
        .expect("run uavmeta");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(
        stderr.contains("UAVMETA_NUMERICS=fast")
            && stderr.contains("compatible")
            && !stderr.contains("panicked"),
        "{stderr}"
    );
}
