//! Build script shared by every package that links libtorch: bakes the directory of the libtorch
//! that torch-sys built against into the package's binaries, tests and benchmarks as an rpath, so
//! that they run with no LD_LIBRARY_PATH set, and exports the executable's answer to MKL's vendor
//! question (learner/src/numerics.rs).

pub fn main() {
    // torch-sys has `links = "tch"` and exports its lib dir to direct dependents as this variable.
    if let Ok(dir) = std::env::var("DEP_TCH_LIBTORCH_LIB") {
        // That dir is under the repo's `.libtorch` link (.cargo/config.toml); the rpath names the
        // wheel's own directory, so a binary copied out of the repo still finds libtorch.
        let dir = std::fs::canonicalize(&dir).map_or(dir, |real| real.display().to_string());
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
    // MKL's vendor question, answered by uavmeta_learner::numerics so that a pinned MKL branch is
    // the same code on Intel and AMD: kept in the link and exported from the executable, where
    // libtorch's calls through its PLT find it before MKL's own.
    for arg in ["--undefined", "--export-dynamic-symbol"] {
        println!("cargo:rustc-link-arg=-Wl,{arg}=mkl_serv_intel_cpu_true");
    }
}
