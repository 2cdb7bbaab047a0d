//! Pinned numerics: the same config and seed give the same bits on another CPU.
//!
//! libtorch picks its kernels by the CPU it runs on: MKL's sgemm takes AVX-512 paths on Intel
//! CPUs that have it and other paths elsewhere, and ATen's vectorised kernels (reductions such
//! as logsumexp, Adam's updates) use 512-bit vectors where the CPU has them. Different vector
//! widths sum in different orders, so a dataset or checkpoint made on one machine differed in its
//! last bits from another's, and training amplified that into another results table. [`pin`] sets
//! the environment both read once, before libtorch starts, in one of three modes chosen by
//! `UAVMETA_NUMERICS`:
//!
//! | mode | MKL | ATen | same bits on |
//! | --- | --- | --- | --- |
//! | `avx2` (default) | `MKL_CBWR=AVX2,STRICT` | `ATEN_CPU_CAPABILITY=avx2` | every Intel CPU with AVX2, with or without AVX-512 (measured); AMD CPUs too, by the same MKL code (not yet run on one) |
//! | `compatible` | `MKL_CBWR=COMPATIBLE,STRICT` | `ATEN_CPU_CAPABILITY=avx2` | the same, with SSE2 code in MKL (1.7-1.9x slower) |
//! | `native` | as the CPU dispatches | as the CPU dispatches | this machine only |
//!
//! MKL honours a named branch (AVX2, AVX512) only where it believes it runs on an Intel CPU;
//! elsewhere it keeps its own dispatch in reproducible (STRICT) mode, and an Intel Xeon and an AMD
//! EPYC ran the same reproduction to other learned numbers under AVX2. It asks one function,
//! `mkl_serv_intel_cpu_true`, which libtorch calls through its PLT, so the definition the
//! executable exports is the one that answers ([`mkl_serv_intel_cpu_true`], exported by
//! build/rpath.rs): where `MKL_CBWR` names a branch it answers yes on every CPU, and the branch is
//! the same code on every vendor. AVX2 costs nothing measurable, COMPATIBLE 1.7-1.9x
//! (docs/BENCHMARKS.md, "Pinned numerics"), hence the default. `ONEDNN_MAX_CPU_ISA` is capped at
//! AVX2 likewise for the oneDNN kernels libtorch may use. A variable the environment already sets
//! is left as it is.

use std::ffi::c_int;
use std::sync::OnceLock;

/// The variable that chooses the mode: `avx2` (also when unset), `compatible` or `native`.
pub const MODE_VARIABLE: &str = "UAVMETA_NUMERICS";

/// The modes [`pin`] knows, and what each sets.
pub const MODES: [(&str, &[(&str, &str)]); 3] = [
    (
        "avx2",
        &[
            ("MKL_CBWR", "AVX2,STRICT"),
            ("ATEN_CPU_CAPABILITY", "avx2"),
            ("ONEDNN_MAX_CPU_ISA", "AVX2"),
        ],
    ),
    (
        "compatible",
        &[
            ("MKL_CBWR", "COMPATIBLE,STRICT"),
            ("ATEN_CPU_CAPABILITY", "avx2"),
            ("ONEDNN_MAX_CPU_ISA", "AVX2"),
        ],
    ),
    ("native", &[]),
];

/// An unknown `UAVMETA_NUMERICS`.
#[derive(Debug, thiserror::Error)]
#[error("{MODE_VARIABLE}={value}: expected avx2 (the default), compatible or native")]
pub struct UnknownMode {
    pub value: String,
}

/// Sets the variables of the mode `UAVMETA_NUMERICS` names (`avx2` when unset) that the
/// environment does not set already. Call it first thing in `main`: before the first libtorch
/// operation, which reads them once, and before any thread starts, since it changes the process
/// environment. Child processes inherit the result.
pub fn pin() -> Result<(), UnknownMode> {
    let mode = std::env::var(MODE_VARIABLE).unwrap_or_else(|_| "avx2".into());
    let (_, settings) = MODES
        .iter()
        .find(|(name, _)| *name == mode)
        .ok_or(UnknownMode {
            value: mode.clone(),
        })?;
    for (name, value) in settings.iter() {
        if std::env::var_os(name).is_none() {
            std::env::set_var(name, value);
        }
    }
    Ok(())
}

/// MKL's question "is this an Intel CPU?", answered for it. MKL (statically inside libtorch)
/// runs the branch `MKL_CBWR` names only where this says yes; MKL's own definition says yes only
/// where CPUID's vendor is `GenuineIntel`, so on an AMD CPU `MKL_CBWR=AVX2,STRICT` fell back to
/// MKL's automatic dispatch and summed in another order. This definition, exported by the
/// executable, comes before libtorch's in the dynamic linker's search: it says yes on every CPU
/// where `MKL_CBWR` names a branch (the pinned modes), and gives MKL's own answer otherwise
/// (`native`, or `MKL_CBWR=AUTO`). The answer is worked out once per process.
#[cfg(target_arch = "x86_64")]
#[no_mangle]
pub extern "C" fn mkl_serv_intel_cpu_true() -> c_int {
    static ANSWER: OnceLock<c_int> = OnceLock::new();
    *ANSWER.get_or_init(|| {
        let cbwr = std::env::var("MKL_CBWR").ok();
        c_int::from(names_a_branch(cbwr.as_deref()) || vendor_is_intel())
    })
}

/// Whether an `MKL_CBWR` value asks for one fixed branch (`AVX2,STRICT`, `COMPATIBLE`, ...)
/// rather than MKL's own choice (unset, `AUTO`, `OFF`).
fn names_a_branch(cbwr: Option<&str>) -> bool {
    let branch = cbwr
        .and_then(|value| value.split(',').next())
        .map(str::trim);
    branch.is_some_and(|b| {
        !b.is_empty() && !["AUTO", "OFF"].iter().any(|m| b.eq_ignore_ascii_case(m))
    })
}

/// MKL's own test: CPUID leaf 0 names the vendor `GenuineIntel`.
#[cfg(target_arch = "x86_64")]
fn vendor_is_intel() -> bool {
    #[allow(unused_unsafe)] // an unsafe fn in older Rust releases, safe in newer ones
    let leaf = unsafe { std::arch::x86_64::__cpuid(0) };
    [leaf.ebx, leaf.edx, leaf.ecx] == [0x756e_6547, 0x4965_6e69, 0x6c65_746e]
}

#[cfg(test)]
mod tests {
    use super::{names_a_branch, MODES};

    #[test]
    fn a_named_branch_is_one_mkl_must_honour_on_every_cpu() {
        for named in ["AVX2,STRICT", "AVX2", "COMPATIBLE,STRICT", "avx512"] {
            assert!(names_a_branch(Some(named)), "{named}");
        }
        for own in [
            None,
            Some(""),
            Some("AUTO"),
            Some("auto,STRICT"),
            Some("OFF"),
        ] {
            assert!(!names_a_branch(own), "{own:?}");
        }
    }

    /// `.cargo/config.toml` gives the processes cargo runs (tests, benches) the default mode's
    /// settings; they must be this table's, or the tests would check other numerics than the
    /// binary's.
    #[test]
    fn cargo_runs_processes_with_the_default_mode() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../.cargo/config.toml");
        let text = std::fs::read_to_string(path).expect("read .cargo/config.toml");
        let config: toml::Table = text.parse().expect(".cargo/config.toml is TOML");
        let env = config["env"].as_table().expect("[env]");
        let (_, default) = MODES
            .iter()
            .find(|(mode, _)| *mode == "avx2")
            .expect("avx2");
        for (name, value) in default.iter() {
            assert_eq!(
                env.get(*name).and_then(|v| v.as_str()),
                Some(*value),
                ".cargo/config.toml [env] {name}"
            );
        }
    }
}
