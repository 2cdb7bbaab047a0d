//! The Python package (python/, `import uavmeta`) tested by its real consumers: pytest runs
//! python/tests in the virtualenv where `make python` installs the package beside gymnasium,
//! numpy, safetensors and stable-baselines3 (tests/interop-requirements.txt), with this build's `uavmeta`
//! binary for the comparisons with `uavmeta env rollout --trace` and `uavmeta collect`.
//! Without the package or its consumers the test is skipped with the reason, except under
//! `CI=true`, where it fails.

mod support;

use std::process::Command;

const REPO: &str = env!("CARGO_MANIFEST_DIR");

#[test]
fn the_python_package_passes_its_pytest_suite() {
    let python = support::venv_python();
    let consumers = "uavmeta, gymnasium, numpy, safetensors, pytest, stable_baselines3";
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
