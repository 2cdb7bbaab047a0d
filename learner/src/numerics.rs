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
//! | `avx2` (default) | `MKL_CBWR=AVX2,STRICT` | `ATEN_CPU_CAPABILITY=avx2` | every Intel CPU with AVX2, with or without AVX-512; every AMD CPU of one MKL dispatch; not Intel and AMD |
//! | `compatible` | `MKL_CBWR=COMPATIBLE,STRICT` | `ATEN_CPU_CAPABILITY=avx2` | every x86-64 CPU with AVX2, Intel or AMD |
//! | `native` | as the CPU dispatches | as the CPU dispatches | this machine only |
//!
//! MKL honours its named branches (AVX2, AVX512) only on Intel CPUs; on others it runs its
//! automatic dispatch in reproducible (STRICT) mode, and only COMPATIBLE (SSE2 code) is the same
//! code on both vendors: an Intel Xeon and an AMD EPYC ran the same reproduction to other
//! learned numbers under AVX2. COMPATIBLE makes training 1.7-1.9x slower on both, AVX2 costs
//! nothing measurable (docs/BENCHMARKS.md, "Pinned numerics"), hence the default. `ONEDNN_MAX_CPU_ISA`
//! is capped at AVX2 likewise for the oneDNN kernels libtorch may use. A variable the
//! environment already sets is left as it is.

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

#[cfg(test)]
mod tests {
    use super::MODES;

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
