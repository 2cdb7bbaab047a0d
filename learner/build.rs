//! The rpath every libtorch package gets (build/rpath.rs), and libtorch's fused Adam kernel made
//! callable from Rust (csrc/fused_adam.cpp, `uavmeta_learner::optim`), compiled against the
//! headers of the libtorch torch-sys links.

#[path = "../build/rpath.rs"]
mod rpath;

use std::path::PathBuf;

fn main() {
    rpath::main();
    println!("cargo:rerun-if-changed=csrc/fused_adam.cpp");
    let lib = std::env::var("DEP_TCH_LIBTORCH_LIB")
        .expect("torch-sys exports its libtorch lib dir (links = \"tch\")");
    let root = PathBuf::from(lib).join("..");
    let include = root.join("include");
    cc::Build::new()
        .cpp(true)
        .pic(true)
        .warnings(false)
        .include(&include)
        .include(include.join("torch/csrc/api/include"))
        .flag("-std=c++17")
        .flag("-D_GLIBCXX_USE_CXX11_ABI=1")
        .flag("-DGLOG_USE_GLOG_EXPORT")
        // As torch-sys (Cargo.toml): no `-g` for C++ that no one steps through.
        .debug(false)
        .file("csrc/fused_adam.cpp")
        .compile("uavmeta_fused_adam");
}
