//! The Python package (python/, `import uavmeta`) tested by its real consumers: pytest runs
//! python/tests in the virtualenv where `make python` installs the package beside gymnasium,
//! numpy and stable-baselines3 (tests/interop-requirements.txt), with this build's `uavmeta`
//! binary for the comparisons with `uavmeta env rollout --trace` and `uavmeta collect`.
//! Without the package or its consumers the test is skipped with the reason, except under
//! `CI=true`, where it fails.

use std::path::{Path, PathBuf};
use std::process::Command;

const REPO: &str = env!("CARGO_MANIFEST_DIR");

/// The virtualenv's Python, found as tests/interop.rs finds it: VIRTUAL_ENV, else the venv
/// holding the `.libtorch` link's target, else python3 on PATH.
fn python() -> PathBuf {
    if let Some(venv) = std::env::var_os("VIRTUAL_ENV") {
        return PathBuf::from(venv).join("bin/python");
    }
    match std::fs::canonicalize(Path::new(REPO).join(".libtorch"))
        .ok()
        .and_then(|torch| torch.ancestors().nth(4).map(Path::to_path_buf))
    {
        Some(venv) if venv.join("bin/python").exists() => venv.join("bin/python"),
        _ => PathBuf::from("python3"),
    }
}

/// Whether the package and its test consumers import; the caller skips if not, but under
/// `CI=true` the test fails.
fn installed(python: &Path) -> bool {
    let imported = Command::new(python)
        .args(["-c", "import uavmeta, gymnasium, numpy, pytest, stable_baselines3"])
        .output();
    let why = match imported {
        Ok(out) if out.status.success() => return true,
        Ok(out) => String::from_utf8_lossy(&out.stderr).into_owned(),
        Err(e) => e.to_string(),
    };
    let why = format!(
        "{} cannot import the package and its consumers (`make python` installs them): {why}",
        python.display()
    );
    assert!(
        std::env::var("CI").map_or(true, |ci| ci != "true"),
        "required under CI=true: {why}"
    );
    eprintln!("skipped: {why}");
    false
}

#[test]
fn the_python_package_passes_its_pytest_suite() {
    let python = python();
    if !installed(&python) {
        return;
    }
    let out = Command::new(&python)
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "python/tests"])
        .current_dir(REPO)
        .env("UAVMETA_BIN", env!("CARGO_BIN_EXE_uavmeta"))
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
