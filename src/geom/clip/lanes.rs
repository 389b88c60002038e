//! The AVX-512 form of [`super::clip_split`]: the polygon in vector
//! lanes, one plane per vector division and compress (see the
//! declaration in the parent module for how it keeps the same bits).

use super::Aabb;
use glam::Vec3;
use std::arch::x86_64::*;

/// Vertices the lanes hold.
const LANES: u32 = 8;

/// A polygon of `n <= LANES` vertices: coordinate `k` of vertex `j` in
/// lane `j` of `c[k]`. Lanes from `n` on hold anything.
#[derive(Clone, Copy)]
struct Poly {
    c: [__m512d; 3],
    n: u32,
}

impl Poly {
    /// The lanes that hold vertices, and each edge's start and end
    /// (vertex `j` and `j + 1`, the first again after the last).
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn edges(&self) -> (__mmask8, [__m512d; 3], [__m512d; 3]) {
        let valid = ((1u32 << self.n) - 1) as __mmask8;
        let next = next_lane(self.n);
        let b = self.c.map(|c| _mm512_permutexvar_pd(next, c));
        (valid, self.c, b)
    }
}

/// `SPREAD[m]`: the 4 bits of `m` moved to the even bits 0, 2, 4, 6.
const SPREAD: [u8; 16] = {
    let mut t = [0u8; 16];
    let mut m = 0;
    while m < 16 {
        let mut b = 0;
        while b < 4 {
            t[m] |= (((m >> b) & 1) << (2 * b)) as u8;
            b += 1;
        }
        m += 1;
    }
    t
};

/// Each lane's next lane around a polygon of `n` vertices (`j + 1`,
/// and 0 after the last), as a permutation index.
#[inline]
#[target_feature(enable = "avx512f")]
fn next_lane(n: u32) -> __m512i {
    const NEXT: [[i64; 8]; 9] = {
        let mut t = [[0i64; 8]; 9];
        let mut n = 1;
        while n <= 8 {
            let mut j = 0;
            while j < 8 {
                t[n][j] = if j + 1 < n { j as i64 + 1 } else { 0 };
                j += 1;
            }
            n += 1;
        }
        t
    };
    // SAFETY: `NEXT[n]` is 64 bytes, the unaligned load's size (the
    // index checks `n <= 8`).
    unsafe { _mm512_loadu_si512(NEXT[n as usize].as_ptr().cast()) }
}

/// Each edge `a → b`'s crossing of the plane `AXIS = pl`, as the scalar
/// `crossing` computes it (meaningless where the edge does not cross).
#[inline]
#[target_feature(enable = "avx512f")]
fn crossings<const AXIS: usize>(a: &[__m512d; 3], b: &[__m512d; 3], pl: __m512d) -> [__m512d; 3] {
    let t = _mm512_div_pd(_mm512_sub_pd(pl, a[AXIS]), _mm512_sub_pd(b[AXIS], a[AXIS]));
    let mut q = [pl; 3];
    for k in 0..3 {
        if k != AXIS {
            q[k] = _mm512_add_pd(a[k], _mm512_mul_pd(_mm512_sub_pd(b[k], a[k]), t));
        }
    }
    q
}

/// Clips `p` to `p[AXIS] >= plane` (`ABOVE`) or `<= plane`, as
/// `Polygon::clip_into` does; `None` when the result would not fit in
/// the lanes.
#[target_feature(enable = "avx512f")]
fn clip<const AXIS: usize, const ABOVE: bool>(p: &Poly, plane: f64) -> Option<Poly> {
    let (valid, a, b) = p.edges();
    let pl = _mm512_set1_pd(plane);
    let (ina, inb) = if ABOVE {
        (
            _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, a[AXIS], pl),
            _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, b[AXIS], pl),
        )
    } else {
        (
            _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, a[AXIS], pl),
            _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, b[AXIS], pl),
        )
    };
    let q = crossings::<AXIS>(&a, &b, pl);
    let cross = ina ^ inb;
    // Edge j's start in slot 2j, its crossing in slot 2j + 1: the
    // order Sutherland–Hodgman writes them in.
    let spread = |m: u8| usize::from(m & 15);
    let k_lo = SPREAD[spread(ina)] | SPREAD[spread(cross)] << 1;
    let k_hi = SPREAD[spread(ina >> 4)] | SPREAD[spread(cross >> 4)] << 1;
    let (n_lo, n_hi) = (k_lo.count_ones(), k_hi.count_ones());
    if n_lo + n_hi > LANES {
        return None;
    }
    let lo_idx = _mm512_set_epi64(11, 3, 10, 2, 9, 1, 8, 0);
    let hi_idx = _mm512_set_epi64(15, 7, 14, 6, 13, 5, 12, 4);
    // Lane j of the result: lane j of the kept low half, then lane
    // j − n_lo of the kept high half (index 8 + j − n_lo).
    let lane = _mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0);
    let from_hi = _mm512_cmpge_epi64_mask(lane, _mm512_set1_epi64(i64::from(n_lo)));
    let join = _mm512_mask_add_epi64(lane, from_hi, lane, _mm512_set1_epi64(8 - i64::from(n_lo)));
    let c = [0, 1, 2].map(|k| {
        let lo = _mm512_maskz_compress_pd(k_lo, _mm512_permutex2var_pd(a[k], lo_idx, q[k]));
        let hi = _mm512_maskz_compress_pd(k_hi, _mm512_permutex2var_pd(a[k], hi_idx, q[k]));
        _mm512_permutex2var_pd(lo, join, hi)
    });
    Some(Poly { c, n: n_lo + n_hi })
}

/// The scalar `clip_split_axis` in lanes; `None` when the polygon
/// outgrows them.
#[target_feature(enable = "avx512f")]
pub(super) fn clip_split_axis<const AXIS: usize>(
    tri: &[Vec3; 3],
    cell: &Aabb,
    known: &Aabb,
    pos: f32,
) -> Option<[Option<Aabb>; 2]> {
    let tb = Aabb::of_triangle(tri);
    if !cell.overlaps(&tb) {
        return Some([None, None]);
    }
    let coord = |k: usize| {
        let v = |i: usize| f64::from(tri[i][k]);
        _mm512_set_pd(0.0, 0.0, 0.0, 0.0, 0.0, v(2), v(1), v(0))
    };
    let mut p = Poly {
        c: [coord(0), coord(1), coord(2)],
        n: 3,
    };
    // The planes `Polygon::clip_to_box` clips to, in its order.
    let cb = super::crossed(&tb, cell, known);
    macro_rules! plane {
        ($axis:literal) => {
            if cb.min[$axis] < cell.min[$axis] && p.n > 0 {
                p = clip::<$axis, true>(&p, f64::from(cell.min[$axis]))?;
            }
            if cb.max[$axis] > cell.max[$axis] && p.n > 0 {
                p = clip::<$axis, false>(&p, f64::from(cell.max[$axis]))?;
            }
        };
    }
    plane!(0);
    plane!(1);
    plane!(2);
    if p.n == 0 {
        return Some([None, None]);
    }
    let (lo, hi) = split::<AXIS>(&p, f64::from(pos));
    Some(finish::<AXIS>(lo, hi, cell, &tb, pos))
}

/// Both halves' `f64` bounds of `p` (`n > 0`) split by `AXIS = plane`:
/// each side's vertices and each edge's crossing where the edge changes
/// side. Lanes 0–2 are the left half's x, y, z, lanes 3–5 the right
/// half's; a half with no point has `+∞` minima and `−∞` maxima.
#[target_feature(enable = "avx512f")]
fn split<const AXIS: usize>(p: &Poly, plane: f64) -> (__m512d, __m512d) {
    let (valid, a, b) = p.edges();
    let pl = _mm512_set1_pd(plane);
    let q = crossings::<AXIS>(&a, &b, pl);
    let al = _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, a[AXIS], pl);
    let ar = _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, a[AXIS], pl);
    let bl = _mm512_mask_cmp_pd_mask::<_CMP_LE_OQ>(valid, b[AXIS], pl);
    let br = _mm512_mask_cmp_pd_mask::<_CMP_GE_OQ>(valid, b[AXIS], pl);
    let inf = _mm512_set1_pd(f64::INFINITY);
    let ninf = _mm512_set1_pd(f64::NEG_INFINITY);
    // Per side and coordinate, the kept vertices and crossings in one
    // vector: `lo[3s + k]`, `hi[3s + k]`.
    let mut lo = [inf; 6];
    let mut hi = [ninf; 6];
    for (s, (on, cross)) in [(al, al ^ bl), (ar, ar ^ br)].into_iter().enumerate() {
        for k in 0..3 {
            lo[3 * s + k] = _mm512_min_pd(
                _mm512_mask_blend_pd(on, inf, a[k]),
                _mm512_mask_blend_pd(cross, inf, q[k]),
            );
            hi[3 * s + k] = _mm512_max_pd(
                _mm512_mask_blend_pd(on, ninf, a[k]),
                _mm512_mask_blend_pd(cross, ninf, q[k]),
            );
        }
    }
    (reduce6::<true>(lo, inf), reduce6::<false>(hi, ninf))
}

/// The six vectors' minima (`MIN`) or maxima in lanes 0–5 (lanes 6 and
/// 7 hold `pad`'s): halves, then quarters, then pairs of lanes, folded
/// across vectors as they shrink.
#[inline]
#[target_feature(enable = "avx512f")]
fn reduce6<const MIN: bool>(v: [__m512d; 6], pad: __m512d) -> __m512d {
    let op = |x: __m512d, y: __m512d| {
        if MIN {
            _mm512_min_pd(x, y)
        } else {
            _mm512_max_pd(x, y)
        }
    };
    // 256-bit halves: h[i] holds v[2i]'s folded half in its low 256
    // bits and v[2i + 1]'s in its high 256 bits.
    let fold = |x: __m512d, y: __m512d| {
        op(
            _mm512_shuffle_f64x2::<0b01_00_01_00>(x, y),
            _mm512_shuffle_f64x2::<0b11_10_11_10>(x, y),
        )
    };
    let h = [fold(v[0], v[1]), fold(v[2], v[3]), fold(v[4], v[5]), pad];
    // 128-bit quarters: g0 holds, in 128-bit lane j, vector j's folded
    // pair; g1 those of v[4], v[5] and the padding.
    let quarter = |x: __m512d, y: __m512d| {
        op(
            _mm512_shuffle_f64x2::<0b10_00_10_00>(x, y),
            _mm512_shuffle_f64x2::<0b11_01_11_01>(x, y),
        )
    };
    let g0 = quarter(h[0], h[1]);
    let g1 = quarter(h[2], h[3]);
    // Pairs: folding the two values of each 128-bit lane leaves, in
    // 128-bit lane j of `e`, vector j's result (from g0) and vector
    // 4 + j's (from g1); the permutation puts vector i's in lane i.
    let e = op(_mm512_unpacklo_pd(g0, g1), _mm512_unpackhi_pd(g0, g1));
    _mm512_permutexvar_pd(_mm512_set_epi64(7, 5, 3, 1, 6, 4, 2, 0), e)
}

/// Rounded outward to `f32` (directed rounding, as `f32_round_down` and
/// `f32_round_up`), intersected with each half of `cell` and with
/// `tb`; `None` for an empty half. Equal to `Bounds64::finish`.
#[inline]
#[target_feature(enable = "avx512f")]
fn finish<const AXIS: usize>(
    lo: __m512d,
    hi: __m512d,
    cell: &Aabb,
    tb: &Aabb,
    pos: f32,
) -> [Option<Aabb>; 2] {
    let lo = _mm512_cvt_roundpd_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(lo);
    let hi = _mm512_cvt_roundpd_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(hi);
    let (left, right) = cell.split(AXIS, pos);
    let pair = |a: Vec3, b: Vec3| _mm256_set_ps(0.0, 0.0, b.z, b.y, b.x, a.z, a.y, a.x);
    let cmin = pair(left.min, right.min);
    let cmax = pair(left.max, right.max);
    let tmin = pair(tb.min, tb.min);
    let tmax = pair(tb.max, tb.max);
    // `max`/`min` by comparison as in `Bounds64::finish`; which zero a
    // tie keeps does not matter, `+ 0.0` drops its sign.
    let lo = _mm256_max_ps(_mm256_max_ps(lo, cmin), tmin);
    let hi = _mm256_min_ps(_mm256_min_ps(hi, cmax), tmax);
    let zero = _mm256_setzero_ps();
    let (lo, hi) = (_mm256_add_ps(lo, zero), _mm256_add_ps(hi, zero));
    let empty = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(lo, hi));
    let mut l = [0f32; 8];
    let mut h = [0f32; 8];
    // SAFETY: both arrays are 8 `f32`s, the unaligned stores' size.
    unsafe {
        _mm256_storeu_ps(l.as_mut_ptr(), lo);
        _mm256_storeu_ps(h.as_mut_ptr(), hi);
    }
    let side = |s: usize| {
        (empty >> (3 * s) & 7 == 0).then(|| {
            Aabb::new(
                Vec3::new(l[3 * s], l[3 * s + 1], l[3 * s + 2]),
                Vec3::new(h[3 * s], h[3 * s + 1], h[3 * s + 2]),
            )
        })
    };
    [side(0), side(1)]
}
