//! The renderer and the CLI agree with brute force on the shipped scenes at
//! small resolutions: the per-pixel hits, the image, `--dump-t`, and the
//! `hits`/`checksum` figures of `--json`.

mod common;

use common::{fresh_temp_dir, slimkd};
use slimkd::build::{self, Algorithm, BuildConfig};
use slimkd::render::{self, Camera, Shading};
use slimkd::scene::{self, TriangleColumns};
use slimkd::trace::{BruteForce, TreeTracer};
use slimkd::tree::TreeIr;
use std::path::{Path, PathBuf};

fn manifest(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// A shipped scene (`scenes/NAME.obj`), its path and its default tree.
fn shipped(name: &str) -> (PathBuf, TriangleColumns, TreeIr) {
    let path = manifest(&format!("scenes/{name}.obj"));
    let (scene, _) = scene::load_obj(&path).unwrap();
    let tree = build::build(&scene, &BuildConfig::default(), Algorithm::WaldHavran, None).unwrap();
    (path, scene, tree)
}

#[test]
fn frames_match_brute_force_on_every_shipped_view() {
    let views =
        render::parse_views(&std::fs::read_to_string(manifest("scenes/views.txt")).unwrap())
            .unwrap();
    for name in ["nexuiz_dieselpower", "bunny_npm"] {
        let (path, scene, tree) = shipped(name);
        tree.validate(&scene).unwrap();
        let tracer = TreeTracer {
            tree: &tree,
            scene: &scene,
        };
        let mut n_views = 0;
        for id in ["1", "2", "3"] {
            let view = render::find_view(&views, &path, id).unwrap();
            let cam = Camera::from_view(view, 40, 32);
            let got = render::trace_frame(&tracer, &cam);
            let want = render::trace_frame(&BruteForce(&scene), &cam);
            assert_eq!(got.hits, want.hits, "{name} view {id}");
            assert!(
                want.n_hits() > 40 * 32 / 2,
                "{name} view {id}: the view should mostly hit"
            );
            let a = render::shade(&got, &cam, &scene, Shading::EyeLight);
            let b = render::shade(&want, &cam, &scene, Shading::EyeLight);
            assert_eq!(a.rgb, b.rgb);
            n_views += 1;
        }
        assert_eq!(n_views, 3);
        // The default camera sees the scene too.
        let cam = Camera::default_for(&tree.bounds, 24, 24);
        let got = render::trace_frame(&tracer, &cam);
        assert_eq!(
            got.hits,
            render::trace_frame(&BruteForce(&scene), &cam).hits
        );
        assert!(got.n_hits() > 0);
    }
}

#[test]
fn cli_dump_t_and_json_match_brute_force() {
    let dir = fresh_temp_dir("cli");
    let scene_path = manifest("scenes/bunny_npm.obj");
    let views = manifest("scenes/views.txt");
    let dump = dir.join("t.f32");
    let img = dir.join("img.png");
    let exr = dir.join("img.exr");
    // `slimkd render` of view 3 at 37×23 with `options`: its JSON report.
    let render_view_3 = |options: &[&str]| {
        let mut args = vec![
            "render",
            scene_path.to_str().unwrap(),
            "--views",
            views.to_str().unwrap(),
            "--view",
            "3",
            "--size",
            "37x23",
        ];
        args.extend_from_slice(options);
        args.push("--json");
        let out = slimkd(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    let j = render_view_3(&[
        "--dump-t",
        dump.to_str().unwrap(),
        "-o",
        img.to_str().unwrap(),
    ]);
    for key in [
        "mode",
        "threads",
        "width",
        "height",
        "mrays_per_s",
        "hits",
        "checksum",
    ] {
        assert!(j.get(key).is_some(), "missing {key}");
    }
    assert_eq!(j["width"], 37);
    assert_eq!(j["height"], 23);
    // Packets by default.
    assert_eq!(j["mode"], "packet");

    // Brute force in-process with the same camera.
    let (scene, _) = scene::load_obj(&scene_path).unwrap();
    let all = render::parse_views(&std::fs::read_to_string(&views).unwrap()).unwrap();
    let cam = Camera::from_view(render::find_view(&all, &scene_path, "3").unwrap(), 37, 23);
    let want = render::trace_frame(&BruteForce(&scene), &cam);
    assert_eq!(j["hits"].as_u64().unwrap(), want.n_hits());
    assert_eq!(j["checksum"].as_f64().unwrap(), want.checksum());

    let bytes = std::fs::read(&dump).unwrap();
    assert_eq!(bytes.len(), 37 * 23 * 4);
    let ts: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let want_t: Vec<f32> = want.hits.iter().map(|h| h.t).collect();
    assert_eq!(
        ts.iter().map(|t| t.to_bits()).collect::<Vec<_>>(),
        want_t.iter().map(|t| t.to_bits()).collect::<Vec<_>>()
    );
    assert!(ts.iter().any(|t| t.is_infinite()), "view 3 has misses");

    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&img).unwrap()));
    let reader = decoder.read_info().unwrap();
    assert_eq!((reader.info().width, reader.info().height), (37, 23));

    // The brute-force mode of the CLI reports the same figures, and EXR works.
    let b = render_view_3(&[
        "--mode",
        "brute",
        "--threads",
        "1",
        "-o",
        exr.to_str().unwrap(),
    ]);
    assert_eq!(b["hits"], j["hits"]);
    assert_eq!(b["checksum"], j["checksum"]);
    assert_eq!(b["threads"], 1);
    assert!(exr.exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn cli_reports_errors_with_exit_codes() {
    let out = slimkd(&["build", "/nonexistent/scene.obj"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/scene.obj"), "{err}");

    let dir = fresh_temp_dir("cli-err");
    let bad = dir.join("bad.obj");
    std::fs::write(&bad, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n").unwrap();
    let out = slimkd(&["build", bad.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.obj:4:"), "{err}");

    let out = slimkd(&["render", "default", "--size", "0x5"]);
    assert_eq!(out.status.code(), Some(2));
    let out = slimkd(&["render", "default", "--size", "8x8", "--view", "9"]);
    assert_eq!(out.status.code(), Some(1));
    // A failed image write leaves nothing behind and fails.
    let out = slimkd(&[
        "render",
        "default",
        "--size",
        "8x8",
        "-o",
        dir.join("no/such/dir/x.png").to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn cli_build_json_has_the_figures() {
    let out = slimkd(&["build", "default", "--json", "--threads", "1"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(j["triangles"], 34973);
    assert!(j["nodes_total"].as_u64().unwrap() > 1000);
    assert!(j["refs"].as_u64().unwrap() >= 34973);
    assert!(j["build_s"].as_f64().unwrap() > 0.0);
}

/// A frame's progress (the CLI's bar) ends at exactly 1, with an image
/// size that leaves partial tiles, and watching it changes no hit.
#[test]
fn frame_progress_ends_at_one() {
    let (_, scene, tree) = shipped("bunny_npm");
    let tracer = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    for (w, h) in [(1, 1), (37, 23), (64, 64), (129, 3)] {
        let cam = Camera::default_for(&tree.bounds, w, h);
        let progress = slimkd::progress::Progress::default();
        let got = render::trace_frame_with_progress(&tracer, &cam, Some(&progress));
        assert_eq!(progress.fraction(), 1.0, "{w}x{h}");
        assert_eq!(got.hits, render::trace_frame(&tracer, &cam).hits);
    }
}

/// Shading a mapped file reads the hit triangles' normals from the file's
/// sections (`FileNormals`, nothing copied into columns); it must shade
/// exactly as the scene's columns do, in a plain and in a reordered file
/// (whose hits are input ids, found in the file through its `tri_map`).
#[test]
fn file_normals_shade_as_the_scenes_columns() {
    let scene = common::kd::load_scene("nexuiz_dieselpower.obj");
    let tree = common::kd::std_tree(&scene);
    let views =
        render::parse_views(&std::fs::read_to_string(manifest("scenes/views.txt")).unwrap())
            .unwrap();
    let path = manifest("scenes/nexuiz_dieselpower.obj");
    let cam = Camera::from_view(render::find_view(&views, &path, "1").unwrap(), 48, 40);
    for reorder in [false, true] {
        let file = common::kd::read(&common::kd::write(&tree, &scene, reorder));
        assert_eq!(file.is_reordered(), reorder);
        let frame = render::trace_frame(&slimkd::trace::Scalar::new(&file), &cam);
        assert!(
            frame.n_hits() > 48 * 40 / 2,
            "the camera should see the scene"
        );
        let normals = render::FileNormals::new(&file, &frame);
        for hit in frame.hits.iter().filter(|h| h.is_hit()) {
            assert_eq!(
                render::TriangleNormals::normal(&normals, hit.tri.0),
                scene.normal(hit.tri.0),
                "reorder {reorder}, triangle {}",
                hit.tri.0
            );
        }
        for shading in [Shading::EyeLight, Shading::Normals] {
            let a = render::shade(&frame, &cam, &normals, shading);
            let b = render::shade(&frame, &cam, &scene, shading);
            assert_eq!(a.rgb, b.rgb, "reorder {reorder}");
        }
    }
}

/// The AO frame (primary, shadow and AO rays) of every secondary mode,
/// through a mapped file's scalar and packet tracers, lights every pixel
/// exactly as brute force does, and counts the same occluded rays.
#[test]
fn ao_frames_match_brute_force_in_every_mode() {
    use slimkd::format::{self, KdFile, WriteOptions};
    use slimkd::render::{AoOptions, Secondary};
    use slimkd::trace::packet::PacketTracer;
    use slimkd::trace::ropes::{RopeTracer, Ropes};
    use slimkd::trace::wide::{WideBoxes, WideTracer};
    use slimkd::trace::{ClosestHit, KdSource, Scalar};
    let views =
        render::parse_views(&std::fs::read_to_string(manifest("scenes/views.txt")).unwrap())
            .unwrap();
    for name in ["nexuiz_dieselpower", "bunny_npm"] {
        let (path, scene, tree) = shipped(name);
        let options = WriteOptions {
            reorder: true,
            ..Default::default()
        };
        let bytes = format::write_to_vec(&tree, &scene, &options).unwrap();
        let file = KdFile::from_bytes(format::aligned_copy(&bytes)).unwrap();
        let view = render::find_view(&views, &path, "1").unwrap();
        let cam = Camera::from_view(view, 48, 40);
        let bounds = scene.bounds();
        let want = render::trace_ao_frame(
            &BruteForce(&scene),
            &cam,
            &bounds,
            |_| &scene,
            &AoOptions {
                spp: 3,
                secondary: Secondary::Single,
            },
        );
        assert!(want.times.shadow_rays > 1000 && want.times.ao_rays == 3 * want.times.shadow_rays);
        assert!(want.times.ao_occluded > 0 && want.times.ao_occluded < want.times.ao_rays);
        let scalar = Scalar::new(&file);
        let packet = PacketTracer::new(&file);
        let ropes = Ropes::new(file.walk()).unwrap();
        let rope_tracer = RopeTracer::new(&file, &ropes);
        let boxes = WideBoxes::new(file.walk()).unwrap();
        let wide_tracer = WideTracer::new(&file, &boxes);
        let tracers: [&dyn ClosestHit; 4] = [&scalar, &packet, &rope_tracer, &wide_tracer];
        for tracer in tracers {
            for secondary in [Secondary::Single, Secondary::Packet, Secondary::FromHit] {
                let got = render::trace_ao_frame(
                    tracer,
                    &cam,
                    &bounds,
                    |buf| render::FileNormals::new(&file, buf),
                    &AoOptions { spp: 3, secondary },
                );
                assert_eq!(got.primary.hits, want.primary.hits, "{name} {secondary:?}");
                assert_eq!(got.light, want.light, "{name} {secondary:?}");
                assert_eq!(got.times.shadowed, want.times.shadowed);
                assert_eq!(got.times.ao_occluded, want.times.ao_occluded);
                let image = render::shade_ao(&got);
                assert_eq!(image.rgb.len(), 48 * 40);
            }
        }
    }
}

/// `frame_rays` gives the rays an AO frame traces: every pixel's primary
/// ray once, the first 16 a 4×4 block; as many shadow and AO rays as the
/// frame traced, blocked as often as the frame counted.
#[test]
fn frame_rays_are_the_frames_rays() {
    use slimkd::render::{AoOptions, Secondary};
    use slimkd::trace::ClosestHit;
    let views =
        render::parse_views(&std::fs::read_to_string(manifest("scenes/views.txt")).unwrap())
            .unwrap();
    let (path, scene, tree) = shipped("nexuiz_dieselpower");
    let tracer = TreeTracer {
        tree: &tree,
        scene: &scene,
    };
    // Sides that are no multiple of the tile or the block.
    let cam = Camera::from_view(render::find_view(&views, &path, "1").unwrap(), 50, 38);
    let bounds = scene.bounds();
    let frame = render::trace_ao_frame(
        &tracer,
        &cam,
        &bounds,
        |_| &scene,
        &AoOptions {
            spp: 3,
            secondary: Secondary::Packet,
        },
    );
    let rays = render::frame_rays(&frame.primary, &cam, &bounds, &&scene, 3);
    let bits = |r: &slimkd::geom::Ray| {
        let (o, d) = (r.origin.to_array(), r.dir.to_array());
        [o[0], o[1], o[2], d[0], d[1], d[2]].map(f32::to_bits)
    };
    let mut want: Vec<_> = (0..38)
        .flat_map(|y| (0..50).map(move |x| (x, y)))
        .map(|(x, y)| bits(&cam.ray(x, y)))
        .collect();
    let mut got: Vec<_> = rays.primary.iter().map(bits).collect();
    want.sort_unstable();
    got.sort_unstable();
    assert_eq!(got, want);
    for (i, r) in rays.primary[..16].iter().enumerate() {
        assert_eq!(
            bits(r),
            bits(&cam.ray(i as u32 % 4, i as u32 / 4)),
            "block ray {i}"
        );
    }
    let t = frame.times;
    assert_eq!(rays.shadow.len() as u64, t.shadow_rays);
    assert_eq!(rays.ao.len() as u64, t.ao_rays);
    let blocked =
        |rays: &[slimkd::geom::Ray]| rays.iter().filter(|r| tracer.occluded(r)).count() as u64;
    assert_eq!(blocked(&rays.shadow), t.shadowed);
    assert_eq!(blocked(&rays.ao), t.ao_occluded);
    assert!(t.shadowed > 0 && t.ao_occluded > 0 && t.ao_occluded < t.ao_rays);
}

#[test]
fn cli_ao_frame_reports_each_ray_kind() {
    let dir = fresh_temp_dir("render_ao");
    let out = dir.join("ao.png");
    let out_s = out.to_str().unwrap();
    let ao_render = |more: &[&str]| {
        let mut args = vec![
            "render",
            "default",
            "--view",
            "1",
            "--size",
            "64x48",
            "--shading",
            "ao",
            "--spp",
            "2",
            "--json",
        ];
        args.extend_from_slice(more);
        slimkd(&args)
    };
    let run = ao_render(&["--secondary", "from-hit", "-o", out_s]);
    let json = common::json(&run);
    let ao = &json["ao"];
    assert_eq!(ao["spp"], 2);
    assert_eq!(ao["secondary"], "from-hit");
    assert_eq!(ao["primary_rays"], 64 * 48);
    let shadow = ao["shadow_rays"].as_u64().unwrap();
    assert!(shadow > 0 && ao["ao_rays"].as_u64().unwrap() == 2 * shadow);
    for key in ["frame_ms", "primary_ms", "context_ms", "shadow_ms", "ao_ms"] {
        assert!(ao[key].as_f64().unwrap() >= 0.0, "{key}");
    }
    // Making the rays takes time, and it is not the frame's.
    assert!(ao["making_ms"].as_f64().unwrap() > 0.0);
    assert!(out.exists());
    // By ropes and over wide boxes: the same picture, the mode named.
    for mode in ["ropes", "wide"] {
        let picture = dir.join(format!("{mode}.png"));
        let run = ao_render(&["--secondary", mode, "-o", picture.to_str().unwrap()]);
        assert_eq!(common::json(&run)["ao"]["secondary"], mode);
        assert_eq!(
            std::fs::read(&picture).unwrap(),
            std::fs::read(&out).unwrap()
        );
    }
    // Without --secondary, a scene this small goes over wide boxes, the
    // same picture again; single rays keep to the tree.
    let picture = dir.join("default.png");
    let run = ao_render(&["-o", picture.to_str().unwrap()]);
    assert_eq!(common::json(&run)["ao"]["secondary"], "wide");
    assert_eq!(
        std::fs::read(&picture).unwrap(),
        std::fs::read(&out).unwrap()
    );
    let run = ao_render(&["--mode", "single"]);
    assert_eq!(common::json(&run)["ao"]["secondary"], "packet");
    // --spp without --shading ao is a usage error.
    let run = slimkd(&["render", "default", "--spp", "4"]);
    assert_eq!(run.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&run.stderr).contains("--shading ao"));
    // --dump-rays writes the frame's rays, as many of each kind as it
    // traced, in the peer's ray files; into a folder that is not there,
    // none of them and a clear error.
    let prefix = dir.join("frame");
    let dump = |prefix: &Path| ao_render(&["--dump-rays", prefix.to_str().unwrap()]);
    let run = dump(&prefix);
    let ao = &common::json(&run)["ao"];
    for (kind, key) in [
        ("primary", "primary_rays"),
        ("shadow", "shadow_rays"),
        ("ao", "ao_rays"),
    ] {
        let rays = slimkd::trace::rays::read_rays(&dir.join(format!("frame-{kind}.rays"))).unwrap();
        assert_eq!(rays.len() as u64, ao[key].as_u64().unwrap(), "{kind}");
    }
    let missing = dir.join("no-such-folder").join("frame");
    let run = dump(&missing);
    assert_eq!(run.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&run.stderr).contains("no-such-folder"));
    assert!(!dir.join("no-such-folder").exists());
    // Nothing is left besides the three files.
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.starts_with("frame"))
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["frame-ao.rays", "frame-primary.rays", "frame-shadow.rays"]
    );
    let run = slimkd(&["render", "default", "--dump-rays", prefix.to_str().unwrap()]);
    assert_eq!(run.status.code(), Some(2));
}
