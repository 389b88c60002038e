use super::*;

fn unit() -> Aabb {
    Aabb::new(Vec3::ZERO, Vec3::ONE)
}

#[test]
fn inside_is_exact() {
    let t = [
        Vec3::new(0.1, 0.2, 0.3),
        Vec3::new(0.5, 0.2, 0.3),
        Vec3::new(0.1, 0.9, 0.3),
    ];
    assert_eq!(clip_triangle(&t, &unit()), Some(Aabb::of_triangle(&t)));
}

#[test]
fn outside_is_none() {
    let t = [
        Vec3::new(2.0, 2.0, 2.0),
        Vec3::new(3.0, 2.0, 2.0),
        Vec3::new(2.0, 3.0, 2.0),
    ];
    assert_eq!(clip_triangle(&t, &unit()), None);
}

#[test]
fn corner_cut_is_tight() {
    // The triangle x + y <= 2 at z = 0.5 only covers part of the box
    // [1,2]x[0,1]: its clipped bounds are x in [1,2], y in [0,1].
    let t = [
        Vec3::new(0.0, 0.0, 0.5),
        Vec3::new(2.0, 0.0, 0.5),
        Vec3::new(0.0, 2.0, 0.5),
    ];
    let bx = Aabb::new(Vec3::new(1.0, 0.0, 0.0), Vec3::new(2.0, 1.0, 1.0));
    let c = clip_triangle(&t, &bx).unwrap();
    assert_eq!(c.min, Vec3::new(1.0, 0.0, 0.5));
    assert_eq!(c.max, Vec3::new(2.0, 1.0, 0.5));
    // A box above the hypotenuse misses although the bounds overlap.
    let bx = Aabb::new(Vec3::new(1.5, 1.5, 0.0), Vec3::new(2.0, 2.0, 1.0));
    assert_eq!(clip_triangle(&t, &bx), None);
}

#[test]
fn diagonal_result_is_conservative() {
    // Clip a skinny diagonal triangle; every sampled point of the
    // triangle inside the box must lie in the clipped bounds.
    let t = [
        Vec3::new(-0.3, 0.1, 0.17),
        Vec3::new(1.7, 0.9, 0.33),
        Vec3::new(1.1, 1.3, 0.71),
    ];
    let bx = unit();
    let c = clip_triangle(&t, &bx).unwrap();
    assert!(bx.contains(&c));
    for i in 0..=50 {
        for j in 0..=(50 - i) {
            let (u, v) = (i as f64 / 50.0, j as f64 / 50.0);
            let p = t[0].as_dvec3() * (1.0 - u - v) + t[1].as_dvec3() * u + t[2].as_dvec3() * v;
            let inside = (0..3).all(|k| p[k] >= 0.0 && p[k] <= 1.0);
            if inside {
                for k in 0..3 {
                    assert!(p[k] >= f64::from(c.min[k]) - 1e-12);
                    assert!(p[k] <= f64::from(c.max[k]) + 1e-12);
                }
            }
        }
    }
}

/// `clip_split` against `clip_triangle` of each child on a grid of
/// planes through skinny and big triangles: the two agree up to the
/// outward rounding (each contains the other's box shrunk by an ulp
/// margin), both are conservative, and both meet the same children.
#[test]
fn split_matches_two_clips() {
    let tris = [
        [
            Vec3::new(-0.3, 0.1, 0.17),
            Vec3::new(1.7, 0.9, 0.33),
            Vec3::new(1.1, 1.3, 0.71),
        ],
        [
            Vec3::new(0.0, 0.0, 0.5),
            Vec3::new(2.0, 0.0, 0.5),
            Vec3::new(0.0, 2.0, 0.5),
        ],
        [
            Vec3::new(-5.0, 0.5, -3.0),
            Vec3::new(6.0, 0.25, 4.0),
            Vec3::new(0.5, 0.75, 9.0),
        ],
    ];
    let cell = Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 1.0));
    let mut compared = 0;
    for tri in &tris {
        for axis in 0..3 {
            for step in 0..=16 {
                let pos = step as f32 / 16.0;
                let (l, r) = cell.split(axis, pos);
                let got = clip_split(tri, &cell, &cell, axis, pos);
                for (g, child) in got.iter().zip([l, r]) {
                    let want = clip_triangle(tri, &child);
                    let near = |a: &Aabb, b: &Aabb| {
                        (0..3).all(|k| {
                            (a.min[k] - b.min[k]).abs() <= 1e-6
                                && (a.max[k] - b.max[k]).abs() <= 1e-6
                        })
                    };
                    match (g, &want) {
                        (Some(g), Some(w)) => {
                            assert!(child.contains(g));
                            assert!(near(g, w), "{g:?} vs {w:?}");
                            for i in 0..=20 {
                                for j in 0..=(20 - i) {
                                    let (u, v) = (i as f64 / 20.0, j as f64 / 20.0);
                                    let p = tri[0].as_dvec3() * (1.0 - u - v)
                                        + tri[1].as_dvec3() * u
                                        + tri[2].as_dvec3() * v;
                                    let inside = (0..3).all(|k| {
                                        p[k] >= f64::from(child.min[k])
                                            && p[k] <= f64::from(child.max[k])
                                    });
                                    if inside {
                                        for k in 0..3 {
                                            assert!(p[k] >= f64::from(g.min[k]) - 1e-12);
                                            assert!(p[k] <= f64::from(g.max[k]) + 1e-12);
                                        }
                                    }
                                }
                            }
                            compared += 1;
                        }
                        (None, None) => {}
                        // A touch at the plane may round either way.
                        (Some(b), None) | (None, Some(b)) => {
                            assert!(b.max[axis] - b.min[axis] <= 1e-6 || b.is_empty());
                        }
                    }
                }
            }
        }
    }
    assert!(compared > 100, "{compared}");
}

/// A triangle in the plane `x + y + z = 1.5` whose edges each cut one
/// corner off the regular hexagon that plane cuts from the unit cube:
/// `triangle ∩ cube` has 9 vertices, more than the vector lanes hold,
/// so the AVX-512 clip hands it to the scalar code.
#[test]
fn nine_vertex_polygon_clips_alike_everywhere() {
    let c = Vec3::splat(0.5);
    let tri = [
        Vec3::new(0.5, 0.0, -0.5),
        Vec3::new(-0.5, 0.5, 0.0),
        Vec3::new(0.0, -0.5, 0.5),
    ]
    .map(|d| c - d * 1.867);
    let cell = unit();
    let tb = Aabb::of_triangle(&tri);
    let mut poly = Polygon::triangle(&tri);
    let mut scratch = Polygon::EMPTY;
    assert_eq!(poly.clip_to_box(&tb, &cell, &mut scratch).n, 9);
    for axis in 0..3 {
        for pos in [0.0, 0.3, 0.5, 0.77, 1.0] {
            let want = reference::clip_split(&tri, &cell, &cell, axis, pos);
            assert!(want[0].is_some() || want[1].is_some());
            for simd in SimdLevel::available() {
                let got = clip_split_on(simd, &tri, &cell, &cell, axis, pos);
                assert_eq!(got, want, "{} axis {axis} at {pos}", simd.name());
            }
        }
    }
}

/// Coordinates from a small grid (so that vertices often lie exactly on
/// cell faces and planes, and triangles are often axis-aligned) or
/// arbitrary.
fn coord() -> impl proptest::strategy::Strategy<Value = f32> {
    use proptest::prelude::*;
    prop_oneof![(-4i32..=4).prop_map(|i| i as f32 * 0.25), -1.5f32..1.5f32]
}

fn point() -> impl proptest::strategy::Strategy<Value = Vec3> {
    use proptest::prelude::*;
    (coord(), coord(), coord()).prop_map(|(x, y, z)| Vec3::new(x, y, z))
}

/// Whether every sampled point of `tri` inside `child` lies in `got`
/// (`None` meets none of them).
fn covers_samples(tri: &[Vec3; 3], child: &Aabb, got: Option<Aabb>) -> bool {
    const N: usize = 24;
    for i in 0..=N {
        for j in 0..=(N - i) {
            let (u, v) = (i as f64 / N as f64, j as f64 / N as f64);
            let p =
                tri[0].as_dvec3() * (1.0 - u - v) + tri[1].as_dvec3() * u + tri[2].as_dvec3() * v;
            let inside =
                (0..3).all(|k| p[k] >= f64::from(child.min[k]) && p[k] <= f64::from(child.max[k]));
            if !inside {
                continue;
            }
            let Some(g) = got else {
                // A point on the child's face may round out of a touch.
                let on_face = (0..3).any(|k| {
                    p[k] - f64::from(child.min[k]) < 1e-9 || f64::from(child.max[k]) - p[k] < 1e-9
                });
                if on_face {
                    continue;
                }
                return false;
            };
            if !(0..3)
                .all(|k| p[k] >= f64::from(g.min[k]) - 1e-9 && p[k] <= f64::from(g.max[k]) + 1e-9)
            {
                return false;
            }
        }
    }
    true
}

/// A triangle, a cell, an axis and a plane position in the cell.
fn split_case() -> impl proptest::strategy::Strategy<Value = ([Vec3; 3], Aabb, usize, f32)> {
    use proptest::prelude::*;
    (
        point(),
        point(),
        point(),
        point(),
        point(),
        0usize..3,
        0.0f32..=1.0,
    )
        .prop_map(|(a, b, c, p, q, axis, t)| {
            let cell = Aabb::new(p.min(q), p.max(q));
            let pos = cell.min[axis] + (cell.max[axis] - cell.min[axis]) * t;
            let pos = pos.clamp(cell.min[axis], cell.max[axis]) + 0.0;
            ([a, b, c], cell, axis, pos)
        })
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(5_000))]
    /// Clipping only to the faces the known box reaches stays
    /// conservative, nests in the children, and agrees with clipping to
    /// every face the triangle crosses up to the rounding.
    #[test]
    fn known_box_skips_only_faces_that_cut_nothing(
        (tri, cell, axis, pos) in split_case(),
    ) {
        let Some(known) = clip_triangle(&tri, &cell) else {
            return Ok(());
        };
        let (l, r) = cell.split(axis, pos);
        let got = clip_split(&tri, &cell, &known, axis, pos);
        let all = clip_split(&tri, &cell, &cell, axis, pos);
        for ((g, w), child) in got.into_iter().zip(all).zip([l, r]) {
            if let Some(g) = g {
                proptest::prop_assert!(child.contains(&g));
            }
            proptest::prop_assert!(covers_samples(&tri, &child, g), "{:?} in {:?}", g, child);
            match (g, w) {
                (Some(g), Some(w)) => {
                    for k in 0..3 {
                        proptest::prop_assert!((g.min[k] - w.min[k]).abs() <= 1e-5);
                        proptest::prop_assert!((g.max[k] - w.max[k]).abs() <= 1e-5);
                    }
                }
                (None, None) => {}
                // A touch may round either way.
                (Some(b), None) | (None, Some(b)) => {
                    proptest::prop_assert!((0..3).any(|k| b.max[k] - b.min[k] <= 1e-5));
                }
            }
        }
    }
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(20_000))]
    /// The branch-free clip equals the textbook one bit for bit.
    #[test]
    fn branch_free_equals_reference(
        (tri, cell, axis, pos) in split_case(),
    ) {
        proptest::prop_assert_eq!(clip_triangle(&tri, &cell), reference::clip_triangle(&tri, &cell));
        for simd in SimdLevel::available() {
            proptest::prop_assert_eq!(
                clip_split_on(simd, &tri, &cell, &cell, axis, pos),
                reference::clip_split(&tri, &cell, &cell, axis, pos),
                "{}", simd.name()
            );
            // With the triangle's clipped box as the known box, as the
            // builders call it.
            if let Some(known) = clip_triangle(&tri, &cell) {
                proptest::prop_assert_eq!(
                    clip_split_on(simd, &tri, &cell, &known, axis, pos),
                    reference::clip_split(&tri, &cell, &known, axis, pos),
                    "{}", simd.name()
                );
            }
        }
    }
}
