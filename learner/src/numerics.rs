//! Pinned numerics: the same config and seed give the same bits on any x86-64 CPU with AVX2,
//! Intel or AMD, with or without AVX-512.
//!
//! libtorch picks its kernels by the CPU it runs on: MKL's sgemm takes AVX-512 paths on Intel
//! CPUs that have it and AVX2 paths elsewhere, and ATen's vectorised kernels (reductions such as
//! logsumexp, Adam's updates) use 512-bit vectors where the CPU has them. Different vector widths
//! sum in different orders, so a dataset or checkpoint made on one machine differed in its last
//! bits from another's, and training amplified that into another results table. [`pin`] fixes
//! every such choice to AVX2 before libtorch starts:
//!
//! - `MKL_CBWR=AVX2,STRICT`: MKL's conditional numerical reproducibility, the AVX2 code branch
//!   on every CPU, strict mode for bitwise-identical gemm whatever the alignment;
//! - `ATEN_CPU_CAPABILITY=avx2`: ATen's kernels at 256-bit vectors;
//! - `ONEDNN_MAX_CPU_ISA=AVX2`: oneDNN's JIT kernels, where libtorch uses them, likewise.
//!
//! What it costs is measured in docs/BENCHMARKS.md ("Pinned numerics"). A variable the
//! environment already sets is left as it is, and `UAVMETA_NUMERICS=native` turns the pinning off
//! for whoever wants the machine's fastest paths and accepts machine-dependent bits.

/// The variables [`pin`] sets, with their values.
pub const PINNED: [(&str, &str); 3] = [
    ("MKL_CBWR", "AVX2,STRICT"),
    ("ATEN_CPU_CAPABILITY", "avx2"),
    ("ONEDNN_MAX_CPU_ISA", "AVX2"),
];

/// The variable that turns the pinning off when it is `native`.
pub const OPT_OUT: &str = "UAVMETA_NUMERICS";

/// Sets each of [`PINNED`] that the environment does not set, unless [`OPT_OUT`] is `native`.
/// Call it first thing in `main`: before the first libtorch operation, which reads them once,
/// and before any thread starts, since it changes the process environment. Child processes
/// inherit the result.
pub fn pin() {
    if std::env::var(OPT_OUT).is_ok_and(|v| v == "native") {
        return;
    }
    for (name, value) in PINNED {
        if std::env::var_os(name).is_none() {
            std::env::set_var(name, value);
        }
    }
}
