//! Single rays over three levels of the tree at a time: an in-memory
//! layout of the same tree ([`WideTree`]), in which a *treelet* holds the
//! seven split planes of a node and its descendants two levels down, and
//! the references of the eight cells below them. A treelet step decides
//! all eight cells in the lanes of one AVX2 register, with the scalar
//! walk's decision rule applied level by level in every lane (so the
//! cells visited, their intervals and their order are those of
//! [`super::walk_cells`]), and pushes the visited ones onto the stack in
//! one store, far to near, without a branch on which children the ray
//! visits.
//!
//! A node with a hoisted triangle (a slim tree's type II node) only ever
//! roots a treelet, which tests its triangle when it is entered, as the
//! scalar walk tests it when it visits the node. A leaf, an empty child
//! or a hoisted node below the first level of a treelet ends its planes
//! there: the planes under it pass every lane on their left side and none
//! on their right, so the one cell below keeps the interval of the cell
//! it stands for.
//!
//! The layout is built from any [`Walk`] and kept beside the source; its
//! bytes ([`WideTree::bytes`]) are memory traded for speed, so it is an
//! option of the tracer, never part of the file.

use super::{Hit, KdSource, MARGIN, MAX_STACK, SourceNode, Walk, clip_ray, test_one};
use crate::geom::{Ray, RayPrecomp};
use crate::simd::SimdLevel;
use glam::Vec3;

/// A cell reference: a leaf (its source node, this bit set), a treelet
/// (its index), or nothing.
const LEAF: u32 = 1 << 31;
const EMPTY: u32 = u32::MAX;

/// Bits of the meta word (the eighth split slot): plane `p`'s axis at
/// bits `2p..2p+2`, its pass flag at bit `PASS + p`, and [`HOISTED`].
const PASS: u32 = 14;
const HOISTED: u32 = 1 << 30;

/// Seven split planes and eight cell references: one cache line. Plane 0
/// is the treelet's root, planes `1 + b0` its children, planes
/// `3 + 2·b0 + b1` their children; cell `b0·4 + b1·2 + b2` lies below
/// (bit 0) or above (bit 1) each of them.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Treelet {
    pos: [f32; 8],
    refs: [u32; 8],
}

/// The tree of a [`Walk`] in treelets.
pub struct WideTree {
    lines: Vec<Treelet>,
    /// The hoisted triangle of each treelet whose meta word says so.
    hoisted: Vec<u32>,
    root: u32,
}

impl WideTree {
    /// Lays out the tree of `walk` (its root is node 0).
    pub fn new<'a, W: Walk<'a>>(walk: W) -> WideTree {
        let mut t = WideTree {
            lines: Vec::new(),
            hoisted: Vec::new(),
            root: EMPTY,
        };
        t.root = t.cell(walk, 0);
        t
    }

    /// The layout's bytes (treelets and hoisted triangles), on top of the
    /// source's.
    pub fn bytes(&self) -> usize {
        self.lines.len() * std::mem::size_of::<Treelet>() + self.hoisted.len() * 4
    }

    /// The reference of the cell that node `n` roots.
    fn cell<'a, W: Walk<'a>>(&mut self, w: W, n: u32) -> u32 {
        if n == super::NO_WORD {
            return EMPTY;
        }
        match w.node(n) {
            SourceNode::Leaf(t) if t.is_empty() => EMPTY,
            SourceNode::Leaf(_) => LEAF | n,
            SourceNode::Inner { .. } => self.treelet(w, n),
        }
    }

    fn treelet<'a, W: Walk<'a>>(&mut self, w: W, n: u32) -> u32 {
        let at = self.lines.len();
        self.lines.push(Treelet {
            pos: [0.0; 8],
            refs: [EMPTY; 8],
        });
        self.hoisted.push(EMPTY);
        let mut tl = Treelet {
            pos: [0.0; 8],
            refs: [EMPTY; 8],
        };
        let mut meta = 0u32;
        let mut hoisted = EMPTY;
        self.place(w, n, 0, 0, &mut tl, &mut meta, &mut hoisted);
        tl.pos[7] = f32::from_bits(meta);
        self.lines[at] = tl;
        self.hoisted[at] = hoisted;
        at as u32
    }

    /// Fills the plane of the node `n` at `level` (0–2) on `path` (its
    /// `level` bits from the treelet's root), or, at level 3 or where `n`
    /// cannot be a plane of this treelet, the cell below.
    #[allow(clippy::too_many_arguments)]
    fn place<'a, W: Walk<'a>>(
        &mut self,
        w: W,
        n: u32,
        level: u32,
        path: u32,
        tl: &mut Treelet,
        meta: &mut u32,
        hoisted: &mut u32,
    ) {
        if level < 3 {
            let plane = (1 << level) - 1 + path;
            if n != super::NO_WORD {
                if let SourceNode::Inner {
                    axis,
                    pos,
                    left,
                    right,
                    t_ref,
                } = w.node(n)
                {
                    if level == 0 || t_ref.is_none() {
                        if let Some(t) = t_ref {
                            *meta |= HOISTED;
                            *hoisted = t;
                        }
                        tl.pos[plane as usize] = pos;
                        *meta |= u32::from(axis & 3) << (2 * plane);
                        self.place(w, left, level + 1, path << 1, tl, meta, hoisted);
                        self.place(w, right, level + 1, (path << 1) | 1, tl, meta, hoisted);
                        return;
                    }
                }
            }
            // `n` ends the planes here: every plane below it on this path
            // passes the left side only.
            for l in level..3 {
                let first = (1 << l) - 1 + (path << (l - level));
                for p in first..first + (1 << (l - level)) {
                    *meta |= 1 << (PASS + p);
                }
            }
            tl.refs[(path << (3 - level)) as usize] = self.cell(w, n);
            return;
        }
        tl.refs[path as usize] = self.cell(w, n);
    }
}

/// For each 7-bit mask of planes whose left side the ray visits second,
/// the eight cells from the farthest to the nearest.
const ORDER_REV: [[u8; 8]; 128] = {
    let mut t = [[0u8; 8]; 128];
    let mut f = 0;
    while f < 128 {
        let mut r = 0;
        while r < 8 {
            let b0 = ((r >> 2) & 1) ^ (f & 1);
            let b1 = ((r >> 1) & 1) ^ ((f >> (1 + b0)) & 1);
            let b2 = (r & 1) ^ ((f >> (3 + 2 * b0 + b1)) & 1);
            t[f][7 - r] = (b0 * 4 + b1 * 2 + b2) as u8;
            r += 1;
        }
        f += 1;
    }
    t
};

/// For each 8-bit lane mask, its set lanes in order, then the others.
const COMPRESS: [[u8; 8]; 256] = {
    let mut t = [[0u8; 8]; 256];
    let mut m = 0;
    while m < 256 {
        let mut k = 0;
        let mut i = 0;
        while i < 8 {
            if m & (1 << i) != 0 {
                t[m][k] = i as u8;
                k += 1;
            }
            i += 1;
        }
        let mut i = 0;
        while i < 8 {
            if m & (1 << i) == 0 {
                t[m][k] = i as u8;
                k += 1;
            }
            i += 1;
        }
        m += 1;
    }
    t
};

/// Pending cells: a treelet step pushes up to eight and takes one, and a
/// path visits at most `MAX_STACK` treelets.
const CAP: usize = 8 * MAX_STACK + 8;

/// The wide walk of one ray.
///
/// # Safety
/// The CPU has AVX2, POPCNT, BMI1/2 and LZCNT.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,popcnt,bmi1,bmi2,lzcnt")]
unsafe fn walk_wide<'a, W: Walk<'a>, const ANY: bool>(tree: &WideTree, src: W, ray: &Ray) -> Hit {
    use std::arch::x86_64::*;
    use std::mem::MaybeUninit;

    let inv_dir = Vec3::ONE / ray.dir;
    let Some((t0, t1)) = clip_ray(&src.bounds(), ray, inv_dir) else {
        return Hit::MISS;
    };
    let rp = RayPrecomp::new(ray);
    let mut best = Hit::MISS;
    let mut steps_left = u64::from(src.step_limit());

    let org = _mm256_setr_ps(
        ray.origin.x,
        ray.origin.y,
        ray.origin.z,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    );
    let dir = _mm256_setr_ps(ray.dir.x, ray.dir.y, ray.dir.z, 0.0, 0.0, 0.0, 0.0, 0.0);
    let inv = _mm256_setr_ps(inv_dir.x, inv_dir.y, inv_dir.z, 0.0, 0.0, 0.0, 0.0, 0.0);
    let margin = _mm256_set1_ps(MARGIN);
    let zero = _mm256_setzero_ps();
    let ones = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
    let axis_shift = _mm256_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14);
    let pass_shift = _mm256_setr_epi32(14, 15, 16, 17, 18, 19, 20, 21);
    let empty = _mm256_set1_epi32(EMPTY as i32);
    // Per level: each lane's plane, and whether it lies above it.
    let plane_of = [
        _mm256_setzero_si256(),
        _mm256_setr_epi32(1, 1, 1, 1, 2, 2, 2, 2),
        _mm256_setr_epi32(3, 3, 4, 4, 5, 5, 6, 6),
    ];
    let above = [
        _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, 0, 0, -1, -1, -1, -1)),
        _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, -1, -1, 0, 0, -1, -1)),
        _mm256_castsi256_ps(_mm256_setr_epi32(0, -1, 0, -1, 0, -1, 0, -1)),
    ];

    let mut s_ref = [MaybeUninit::<u32>::uninit(); CAP];
    let mut s_min = [MaybeUninit::<f32>::uninit(); CAP];
    let mut s_max = [MaybeUninit::<f32>::uninit(); CAP];
    let mut sp = 0usize;
    let (mut cur, mut tmin, mut tmax) = (tree.root, t0, t1);
    loop {
        if steps_left == 0 {
            return best;
        }
        steps_left -= 1;
        if cur & LEAF != 0 {
            if let SourceNode::Leaf(tris) = src.node(cur & !LEAF) {
                for i in 0..tris.len() {
                    if test_one::<W, ANY>(src, &rp, ray, tris.get(i), &mut best) {
                        return best;
                    }
                }
            }
        } else if let Some(tl) = tree.lines.get(cur as usize) {
            // SAFETY: a treelet is 64-byte aligned; the loads read its fields.
            let pos = unsafe { _mm256_load_ps(tl.pos.as_ptr()) };
            let meta = tl.pos[7].to_bits();
            if meta & HOISTED != 0 {
                let t = tree.hoisted[cur as usize];
                if test_one::<W, ANY>(src, &rp, ray, t, &mut best) {
                    return best;
                }
            }
            let metav = _mm256_set1_epi32(meta as i32);
            let axes = _mm256_and_si256(_mm256_srlv_epi32(metav, axis_shift), _mm256_set1_epi32(3));
            let pass = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
                _mm256_and_si256(_mm256_srlv_epi32(metav, pass_shift), _mm256_set1_epi32(1)),
                _mm256_set1_epi32(1),
            ));
            let o = _mm256_permutevar8x32_ps(org, axes);
            let d = _mm256_permutevar8x32_ps(dir, axes);
            let iv = _mm256_permutevar8x32_ps(inv, axes);
            let ts_p = _mm256_mul_ps(_mm256_sub_ps(pos, o), iv);
            let on_p = _mm256_cmp_ps::<_CMP_EQ_OQ>(o, pos);
            let below_p = _mm256_cmp_ps::<_CMP_LT_OQ>(o, pos);
            // Whether a plane's right child is visited second: the origin
            // below it, or (origin in it) a direction that is not positive.
            let sec_r = _mm256_blendv_ps(below_p, _mm256_cmp_ps::<_CMP_LE_OQ>(d, zero), on_p);

            let mut lo = _mm256_set1_ps(tmin);
            let mut hi = _mm256_set1_ps(tmax);
            let mut keep = ones;
            for level in 0..3 {
                let idx = plane_of[level];
                let side = above[level];
                let ts = _mm256_permutevar8x32_ps(ts_p, idx);
                let on = _mm256_permutevar8x32_ps(on_p, idx);
                let below = _mm256_permutevar8x32_ps(below_p, idx);
                let ps = _mm256_permutevar8x32_ps(pass, idx);
                let near = _mm256_xor_ps(side, below);
                // The scalar walk's rule: the near child only, the far
                // child only, or both, split at `ts`.
                let near_only = _mm256_or_ps(
                    _mm256_cmp_ps::<_CMP_LE_OQ>(ts, zero),
                    _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_sub_ps(ts, _mm256_mul_ps(ts, margin)), hi),
                );
                let far_only = _mm256_andnot_ps(
                    near_only,
                    _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_add_ps(ts, _mm256_mul_ps(ts, margin)), lo),
                );
                let both = _mm256_andnot_ps(_mm256_or_ps(near_only, far_only), ones);
                let split = _mm256_andnot_ps(_mm256_or_ps(on, ps), ones);
                let drop = _mm256_or_ps(
                    _mm256_and_ps(near_only, _mm256_andnot_ps(near, ones)),
                    _mm256_and_ps(far_only, near),
                );
                keep = _mm256_andnot_ps(_mm256_and_ps(split, drop), keep);
                keep = _mm256_andnot_ps(_mm256_and_ps(ps, side), keep);
                let cut = _mm256_and_ps(split, both);
                hi = _mm256_blendv_ps(hi, _mm256_min_ps(ts, hi), _mm256_and_ps(cut, near));
                lo = _mm256_blendv_ps(lo, _mm256_max_ps(ts, lo), _mm256_andnot_ps(near, cut));
            }
            // SAFETY: `refs` is the second half of the aligned line.
            let refs = unsafe { _mm256_load_si256(tl.refs.as_ptr().cast()) };
            let valid =
                _mm256_andnot_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(refs, empty)), keep);
            // Planes whose left child is visited second.
            let flip = (!_mm256_movemask_ps(sec_r) as u32 & 0x7f) as usize;
            // SAFETY: each table row is 8 bytes, the load's width.
            let rev =
                _mm256_cvtepu8_epi32(unsafe { _mm_loadl_epi64(ORDER_REV[flip].as_ptr().cast()) });
            let vmask = _mm256_movemask_ps(_mm256_permutevar8x32_ps(valid, rev)) as usize;
            // SAFETY: as above.
            let comp =
                _mm256_cvtepu8_epi32(unsafe { _mm_loadl_epi64(COMPRESS[vmask].as_ptr().cast()) });
            let idx = _mm256_permutevar8x32_epi32(rev, comp);
            if sp + 8 > CAP {
                // Only a file that was not validated is this deep.
                return best;
            }
            // SAFETY: `sp + 8 <= CAP`: unaligned stores of 8 lanes within
            // the three arrays.
            unsafe {
                _mm256_storeu_si256(
                    s_ref.as_mut_ptr().add(sp).cast(),
                    _mm256_permutevar8x32_epi32(refs, idx),
                );
                _mm256_storeu_ps(
                    s_min.as_mut_ptr().add(sp).cast(),
                    _mm256_permutevar8x32_ps(lo, idx),
                );
                _mm256_storeu_ps(
                    s_max.as_mut_ptr().add(sp).cast(),
                    _mm256_permutevar8x32_ps(hi, idx),
                );
            }
            sp += vmask.count_ones() as usize;
        }
        // The nearest pending cell that may still hold a hit at or before
        // the best one (the scalar walk's pop).
        loop {
            if sp == 0 {
                return best;
            }
            sp -= 1;
            // SAFETY: entries below the old `sp` were written.
            (cur, tmin, tmax) = unsafe {
                (
                    s_ref[sp].assume_init(),
                    s_min[sp].assume_init(),
                    s_max[sp].assume_init(),
                )
            };
            if tmin - tmin * MARGIN <= best.t {
                break;
            }
        }
    }
}

/// Single rays through a [`WideTree`] of `src`, on AVX2 or better (on a
/// CPU without AVX2 the scalar walk answers).
pub struct WideTracer<'a, S: KdSource + 'a> {
    walk: S::Walk<'a>,
    tree: WideTree,
    level: SimdLevel,
}

impl<'a, S: KdSource> WideTracer<'a, S> {
    /// Lays out `src`'s tree in treelets.
    pub fn new(src: &'a S) -> Self {
        let walk = src.walk();
        WideTracer {
            walk,
            tree: WideTree::new(walk),
            level: SimdLevel::detect(),
        }
    }

    /// The bytes of the layout (on top of the source's).
    pub fn bytes(&self) -> usize {
        self.tree.bytes()
    }

    #[inline(always)]
    fn walk<const ANY: bool>(&self, ray: &Ray) -> Hit {
        #[cfg(target_arch = "x86_64")]
        if self.level != SimdLevel::Baseline {
            // SAFETY: `detect` reports AVX2 or AVX-512 only where every
            // feature `walk_wide` enables is present.
            return unsafe { walk_wide::<_, ANY>(&self.tree, self.walk, ray) };
        }
        super::walk_ray::<_, ANY, false>(self.walk, ray, &mut super::TraceStats::default())
    }
}

impl<'a, S: KdSource> super::ClosestHit for WideTracer<'a, S> {
    fn closest_hit(&self, ray: &Ray) -> Hit {
        self.walk::<false>(ray)
    }

    fn occluded(&self, ray: &Ray) -> bool {
        self.walk::<true>(ray).is_hit()
    }
}
