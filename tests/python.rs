//! The Python package (python/, `import uavmeta`) tested by its real consumers: pytest runs
//! python/tests in the virtualenv where `make python` installs the package beside gymnasium,
//! numpy, safetensors, stable-baselines3, torch and Pillow (tests/interop-requirements.txt), with
//! this build's `uavmeta` binary for the comparisons with `uavmeta env rollout`, `uavmeta eval`
//! and `uavmeta collect`; and the wheel `make wheel` builds, installed with pip into a new
//! virtualenv whose PATH has no Rust toolchain. Without the package or its consumers a test is
//! skipped with the reason, except under `CI=true`, where it fails.

mod support;

use std::path::Path;
use std::process::Command;

const REPO: &str = env!("CARGO_MANIFEST_DIR");

#[test]
fn the_python_package_passes_its_pytest_suite() {
    let python = support::venv_python();
    let consumers = "uavmeta, gymnasium, numpy, safetensors, pytest, stable_baselines3, torch, PIL";
    if !support::python_imports(&python, consumers, "make python") {
        return;
    }
    let out = Command::new(&python)
        .args([
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "python/tests",
        ])
        .current_dir(REPO)
        .env("UAVMETA_BIN", env!("CARGO_BIN_EXE_uavmeta"))
        // One thread for torch, numpy and OpenBLAS, as the binary's libtorch has: beside the
        // other tests on two cores, two threads each only wait for one another.
        .env("OMP_NUM_THREADS", "1")
        .env("OPENBLAS_NUM_THREADS", "1")
        .output()
        .expect("run pytest");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}");
    assert!(
        out.status.success(),
        "pytest python/tests failed:\n{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Every test ran: none may skip here, where the binary and the consumers are present.
    assert!(
        stdout.contains(" passed") && !stdout.contains("skipped"),
        "{stdout}"
    );
}

/// `make wheel`'s command builds an abi3 wheel that pip installs into a fresh virtualenv with no
/// cargo or rustc on the PATH, where it steps, evaluates and loads a dataset-free env.
#[test]
fn the_wheel_installs_and_runs_without_a_rust_toolchain() {
    let python = support::venv_python();
    if !support::python_imports(
        &python,
        "maturin, numpy, gymnasium, safetensors",
        "make interop",
    ) {
        return;
    }
    let bin_dir = python.parent().expect("the venv's bin");
    let dir = tempfile::tempdir().expect("temp dir");
    let wheels = dir.path().join("wheels");
    // The Makefile's `wheel` target, with the wheel written here rather than to target/wheels.
    run(Command::new(bin_dir.join("maturin"))
        .args(["build", "--release", "-m", "python/Cargo.toml", "--out"])
        .arg(&wheels)
        .current_dir(REPO));
    let wheel = std::fs::read_dir(&wheels)
        .expect("the wheels directory")
        .map(|e| e.expect("entry").path())
        .find(|p| p.extension().is_some_and(|e| e == "whl"))
        .expect("a wheel");
    let name = wheel.file_name().unwrap().to_string_lossy().into_owned();
    assert!(name.contains("-abi3-"), "{name}: expected an abi3 wheel");

    let venv = dir.path().join("venv");
    run(Command::new(&python).args(["-m", "venv"]).arg(&venv));

    // No cargo, no rustc: only the venv and the system's own directories.
    let path = format!("{}:/usr/bin:/bin", venv.join("bin").display());
    let no_rust = Command::new("sh")
        .args(["-c", "command -v cargo || command -v rustc || echo none"])
        .env("PATH", &path)
        .output()
        .expect("sh");
    assert_eq!(String::from_utf8_lossy(&no_rust.stdout).trim(), "none");
    run(Command::new(venv.join("bin/python"))
        .args([
            "-m",
            "pip",
            "install",
            "--no-index",
            "--no-deps",
            "--ignore-installed",
            "--no-input",
            "-q",
        ])
        .arg(&wheel)
        .env("PATH", &path)
        .env_remove("CARGO_HOME")
        .env_remove("RUSTUP_HOME"));
    // The wheel's dependencies (numpy, gymnasium, safetensors) come from the test virtualenv's
    // site-packages through a .pth file, as pip would fetch them, so no network. Written after
    // the install: that site-packages holds `make python`'s uavmeta too, which pip would take
    // for this one and skip the wheel; the venv's own site-packages stays first on sys.path.
    let purelib = |python: &Path| {
        let query = "import sysconfig; print(sysconfig.get_paths()['purelib'])";
        run(Command::new(python).args(["-c", query]))
            .trim()
            .to_string()
    };
    let (site, new_site) = (purelib(&python), purelib(&venv.join("bin/python")));
    // addsitedir, so the .pth files there (an editable install's, a chained virtualenv's) count.
    let pth = format!("import site; site.addsitedir({site:?})\n");
    std::fs::write(Path::new(&new_site).join("deps.pth"), pth).expect("pth");
    let script = r#"
import sys, numpy as np, uavmeta
assert uavmeta.__file__.startswith(sys.prefix), uavmeta.__file__
envs = uavmeta.VectorEnv(8, tasks=uavmeta.TaskSampler(lam=(0.0, 900.0)), normalised=True)
obs, info = envs.reset(seed=0)
obs, *_ = envs.step(np.zeros(8, np.int64))
print(uavmeta.evaluate("stalest", 300.0).ret.mean)
"#;
    let out = run(Command::new(venv.join("bin/python"))
        .args(["-c", script])
        .env("PATH", &path)
        .current_dir(dir.path()));
    assert!(out.starts_with('-'), "{out}");
}

/// Runs `command`, failing with its stderr unless it succeeds; returns its stdout.
fn run(command: &mut Command) -> String {
    let out = command.output().expect("spawn");
    assert!(
        out.status.success(),
        "{command:?} failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}
