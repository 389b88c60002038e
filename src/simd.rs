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
    /// The best level this CPU supports.
    pub fn detect() -> SimdLevel {
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
