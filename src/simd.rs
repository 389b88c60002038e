//! Runtime choice of vector instruction sets: kernels are compiled once per
//! level with `#[target_feature]` and chosen by [`SimdLevel::detect`].

/// The vector instruction set a kernel with runtime dispatch uses on this
/// CPU (the packet traverser, the tiny-node sweep of the level builder).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimdLevel {
    /// AVX-512F: 16 `f32` lanes, mask registers.
    Avx512,
    /// AVX2: 8 `f32` lanes.
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
            // Each level's kernels are compiled with the features listed
            // here (`simd_dispatch!`), so it runs only where all of them
            // are reported. POPCNT, BMI1/2 and LZCNT come with every CPU
            // that has AVX2; without them in the target features, a lane
            // mask's `count_ones` compiled to a dozen shifts and masks.
            let base = is_x86_feature_detected!("popcnt")
                && is_x86_feature_detected!("bmi1")
                && is_x86_feature_detected!("bmi2")
                && is_x86_feature_detected!("lzcnt");
            if base
                && is_x86_feature_detected!("avx512f")
                && is_x86_feature_detected!("avx512vl")
                && is_x86_feature_detected!("avx512bw")
                && is_x86_feature_detected!("avx512dq")
            {
                return SimdLevel::Avx512;
            }
            if base && is_x86_feature_detected!("avx2") {
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

    /// The level's name for `SLIMKD_SIMD` and the CLI's output.
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

impl SimdLevel {
    /// `level` if this CPU has it, else the best level it has: what a
    /// dispatch may run without undefined behaviour.
    pub fn usable(level: SimdLevel) -> SimdLevel {
        let best = SimdLevel::detect();
        if level as u8 >= best as u8 {
            level
        } else {
            best
        }
    }
}

/// Evaluates `$body` compiled for the instruction set `$level` (or, if this
/// CPU lacks it, the best one it has; [`SimdLevel::usable`]): the one place
/// where a kernel's per-level copies and their `unsafe` calls are written.
/// `$body` is inlined into one `#[target_feature]` function per level, so
/// that its lane loops (in `#[inline(always)]` functions) are vectorised
/// for that level; in it, the constant `$wide` is `true` on AVX-512 (whose
/// mask registers make some formulations cheaper).
#[macro_export]
macro_rules! simd_dispatch {
    ($level:expr, |$wide:ident| $body:expr) => {{
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq,popcnt,bmi1,bmi2,lzcnt")]
        fn on_avx512<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,popcnt,bmi1,bmi2,lzcnt")]
        fn on_avx2<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        match $crate::simd::SimdLevel::usable($level) {
            #[cfg(target_arch = "x86_64")]
            $crate::simd::SimdLevel::Avx512 => {
                // SAFETY: `usable` returns AVX-512 only if this CPU reported
                // every feature `on_avx512` enables (`SimdLevel::cpu`).
                unsafe {
                    on_avx512(
                        #[inline(always)]
                        || {
                            const $wide: bool = true;
                            $body
                        },
                    )
                }
            }
            #[cfg(target_arch = "x86_64")]
            $crate::simd::SimdLevel::Avx2 => {
                // SAFETY: `usable` returns AVX2 only if this CPU reported
                // every feature `on_avx2` enables (`SimdLevel::cpu`).
                unsafe {
                    on_avx2(
                        #[inline(always)]
                        || {
                            const $wide: bool = false;
                            $body
                        },
                    )
                }
            }
            _ => {
                const $wide: bool = false;
                $body
            }
        }
    }};
}
