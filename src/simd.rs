//! Runtime choice of vector instruction sets: kernels are compiled once per
//! level with `#[target_feature]` and chosen by [`SimdLevel::detect`].

/// The vector instruction set a kernel with runtime dispatch uses on this
/// CPU (the packet traverser, the tiny-node sweep of the level builder).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimdLevel {
    Avx512,
    Avx2,
    /// SSE2 on x86-64, whatever the target offers elsewhere.
    Baseline,
}

impl SimdLevel {
    /// The best level this CPU supports, capped by the environment
    /// variable `SLIMKD_SIMD` (`avx512`, `avx2` or `baseline`), which
    /// exists to measure and test the lower levels on a CPU that has the
    /// higher ones. An unknown value is ignored.
    pub fn detect() -> SimdLevel {
        static LEVEL: std::sync::OnceLock<SimdLevel> = std::sync::OnceLock::new();
        *LEVEL.get_or_init(|| {
            let cpu = Self::cpu();
            match std::env::var("SLIMKD_SIMD")
                .ok()
                .and_then(|v| Self::from_name(&v))
            {
                // A lower level is always available (the enum is ordered
                // best first); a higher one than the CPU's is not.
                Some(cap) if cap as u8 > cpu as u8 => cap,
                _ => cpu,
            }
        })
    }

    /// The best level this CPU supports.
    fn cpu() -> SimdLevel {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return SimdLevel::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return SimdLevel::Avx2;
            }
        }
        SimdLevel::Baseline
    }

    /// The level named `name` (as [`SimdLevel::name`] spells it).
    pub fn from_name(name: &str) -> Option<SimdLevel> {
        [SimdLevel::Avx512, SimdLevel::Avx2, SimdLevel::Baseline]
            .into_iter()
            .find(|l| l.name() == name.trim().to_ascii_lowercase())
    }

    pub fn name(self) -> &'static str {
        match self {
            SimdLevel::Avx512 => "avx512",
            SimdLevel::Avx2 => "avx2",
            SimdLevel::Baseline => "baseline",
        }
    }

    /// Every level this CPU can run (for tests).
    pub fn available() -> Vec<SimdLevel> {
        let best = SimdLevel::detect();
        [SimdLevel::Avx512, SimdLevel::Avx2, SimdLevel::Baseline]
            .into_iter()
            .filter(|l| *l as u8 >= best as u8)
            .collect()
    }
}
