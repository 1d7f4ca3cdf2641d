//! The engine on contract-v2 graphs (the tiny random multi-scale models in
//! tests/fixtures/models/tiny-v2), alone and beside contract-v1 ones: tiling, padding,
//! variants named after their directory, and the loader's checks.

use crate::common;
use crate::model_dirs;

use std::path::Path;

use common::*;
use mcdenoise::engine::{
    albedo, exposure, synthetic_frame, AlbedoPrefilter, Denoiser, Engine, EngineConfig, FeatureSet, InputCompression,
    IoBinding, ModelLoading, Options, Outputs, Precision, Reconstruction, SpecularPyramid, Variant,
};
use model_dirs::*;

fn engine_at(dir: &Path, tile: usize) -> Engine {
    let mut config = EngineConfig::new(dir);
    (config.tile, config.tile_v2) = (tile, tile);
    config.threads = 2;
    Engine::load(&config).expect("models load (is the ONNX Runtime library installed? run scripts/setup)")
}

#[test]
fn tiled_output_equals_whole_frame_output() {
    // 90×70 is not a multiple of the models' size multiple (4): the frame's last row and
    // column are replicated; tiles of 18 are rounded up to 20.
    for cov in [true, false] {
        let frame = synthetic_frame(90, 70, cov);
        let whole = engine_at(&tiny_v2(), 0).denoise(&frame, None, &mut |_| true).unwrap();
        assert_eq!((whole.tiles, whole.variant), (1, if cov { Variant::Full } else { Variant::Nocov }));
        for tile in [16, 18, 32] {
            let tiled = engine_at(&tiny_v2(), tile).denoise(&frame, None, &mut |_| true).unwrap();
            assert!(tiled.tiles >= 9, "tile {tile}: {} tiles", tiled.tiles);
            for c in 0..3 {
                for (name, a, b) in [
                    ("color", &tiled.color[c], &whole.color[c]),
                    ("diffuse", &parts(&tiled).diffuse[c], &parts(&whole).diffuse[c]),
                    ("specular", &parts(&tiled).specular[c], &parts(&whole).specular[c]),
                ] {
                    let d = max_rel_diff(a, b);
                    assert!(d <= 1e-5, "cov {cov}, tile {tile}, {name} {c}: relative difference {d}");
                }
            }
        }
        // Cores split further by the region bound give the same pixels.
        let mut config = EngineConfig::new(tiny_v2());
        (config.tile_v2, config.region_pixels, config.threads) = (1000, Some(40 * 40), 2);
        let bounded = Engine::load(&config).unwrap().denoise(&frame, None, &mut |_| true).unwrap();
        assert!(bounded.tiles >= 6, "{} tiles", bounded.tiles);
        for c in 0..3 {
            let d = max_rel_diff(&bounded.color[c], &whole.color[c]);
            assert!(d <= 1e-5, "cov {cov}, region bound, color {c}: relative difference {d}");
        }
    }
}

#[test]
fn detail_gains_are_read_and_tiles_still_equal_the_whole_frame() {
    let frame = synthetic_frame(90, 70, true);
    let whole = engine_at(&tiny_v2_gain(), 0).denoise(&frame, None, &mut |_| true).unwrap();
    let mut e = engine_at(&tiny_v2_gain(), 18);
    assert!(e.models()[0].detail_gains && !engine_at(&tiny_v2(), 0).models()[0].detail_gains);
    let tiled = e.denoise(&frame, None, &mut |_| true).unwrap();
    assert!(tiled.tiles >= 9, "{} tiles", tiled.tiles);
    for c in 0..3 {
        let d = max_rel_diff(&tiled.color[c], &whole.color[c]);
        assert!(d <= 1e-5, "color {c}: relative difference {d}");
        assert!(tiled.color[c].iter().all(|v| v.is_finite()));
    }
    // A graph with some of the gains but not all is refused by the one missing.
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "full", "model.onnx", &rename(&read(&tiny_v2_gain(), "full", "model.onnx"), "gain_1", "gain_9"));
    let msg = load_error(tmp.path());
    assert!(msg.contains("full/model.onnx") && msg.contains("graph has no `gain_1`"), "{msg}");
}

#[test]
fn the_network_in_stages_gives_the_whole_graphs_output() {
    // tiny-v2 and tiny-v2-gain carry the stage files of their model.onnx
    // (`python -m mcdenoise_train.stages`): front and back per core with a 16-px margin,
    // middle over the frame. The same pixels as the whole graph over each core and its
    // halo, with tiles of every kind (one, interior, edge, sizes off the size multiple).
    for (dir, cov) in [(tiny_v2(), true), (tiny_v2(), false), (tiny_v2_gain(), true)] {
        for (w, h) in [(90, 70), (45, 37), (130, 64)] {
            let frame = synthetic_frame(w, h, cov);
            for tile in [0, 16, 32] {
                let run = |stages: bool| {
                    let mut config = EngineConfig::new(&dir);
                    (config.tile, config.tile_v2, config.threads, config.stages) = (tile, tile, 2, stages);
                    Engine::load(&config).unwrap().denoise(&frame, None, &mut |_| true).unwrap()
                };
                let (staged, whole) = (run(true), run(false));
                assert!(staged.staged && !whole.staged, "{w}x{h}, tile {tile}");
                assert_eq!(staged.tiles, whole.tiles);
                for c in 0..3 {
                    for (name, a, b) in [
                        ("color", &staged.color[c], &whole.color[c]),
                        ("diffuse", &parts(&staged).diffuse[c], &parts(&whole).diffuse[c]),
                        ("specular", &parts(&staged).specular[c], &parts(&whole).specular[c]),
                    ] {
                        let d = max_rel_diff(a, b);
                        assert!(d <= 1e-5, "{w}x{h}, cov {cov}, tile {tile}, {name} {c}: relative difference {d}");
                    }
                }
            }
        }
    }
    // A frame whose pooled features exceed the region bound runs the whole graph per region.
    let mut config = EngineConfig::new(tiny_v2());
    (config.tile_v2, config.region_pixels, config.threads) = (32, Some(40 * 40), 2);
    let bounded = Engine::load(&config).unwrap().denoise(&synthetic_frame(90, 70, true), None, &mut |_| true).unwrap();
    assert!(!bounded.staged);
}

#[test]
fn stage_files_are_checked_against_their_model() {
    let full = tiny_v2().join("full");
    let copy = |dir: &Path, from: &Path, files: &[&str]| {
        for f in files {
            write(dir, "full", f, &std::fs::read(from.join(f)).unwrap());
        }
    };
    // Cut from another model.onnx.
    let tmp = tempfile::tempdir().unwrap();
    copy(tmp.path(), &full, &["model.onnx"]);
    copy(tmp.path(), &tiny_v2_gain().join("full"), &["front.onnx", "middle.onnx", "back.onnx"]);
    let msg = load_error(tmp.path());
    assert!(msg.contains("full/front.onnx") && msg.contains("cut them again with"), "{msg}");
    // One missing.
    let tmp = tempfile::tempdir().unwrap();
    copy(tmp.path(), &full, &["model.onnx", "front.onnx", "middle.onnx"]);
    let msg = load_error(tmp.path());
    assert!(msg.contains("full/back.onnx") && msg.contains("file not found"), "{msg}");
    // None: the whole graph.
    let tmp = tempfile::tempdir().unwrap();
    copy(tmp.path(), &full, &["model.onnx"]);
    let mut config = EngineConfig::new(tmp.path());
    config.threads = 1;
    let out = Engine::load(&config).unwrap().denoise(&synthetic_frame(45, 37, true), None, &mut |_| true).unwrap();
    assert!(!out.staged);
}

#[test]
fn the_output_is_finite_and_the_components_add_up() {
    let out = engine_at(&tiny_v2(), 32).denoise(&synthetic_frame(45, 37, true), None, &mut |_| true).unwrap();
    for c in 0..3 {
        assert!(out.color[c].iter().all(|v| v.is_finite() && *v >= 0.0));
        for i in 0..out.color[c].len() {
            assert!((out.color[c][i] - parts(&out).diffuse[c][i] - parts(&out).specular[c][i]).abs() <= 1e-6);
        }
    }
    // Without its components the color is assembled tile by tile: the same bits.
    let frame = synthetic_frame(45, 37, true);
    let bare = engine_at(&tiny_v2(), 32).denoise_with(&frame, Options::default(), &mut |_| true).unwrap();
    assert!(bare.components.is_none());
    assert!(bare.tiles > 1);
    assert_eq!(bare.color, out.color);
    // Not the noisy input: the kernels filter.
    let noisy = frame.color();
    assert!(max_rel_diff(&out.color[0], &noisy[0]) > 1e-3);
}

#[test]
fn frames_brighter_than_the_training_ones_are_scaled_into_their_range_and_back() {
    let top = exposure::LEVEL_MAX;
    let base = synthetic_frame(45, 37, true);
    let level = exposure::level(&base).unwrap();
    // The same frame in four units: just under the top level and 1000 times darker (both left as
    // they are), and 100 and 1000 times above the top (both brought down to it, so the same
    // network inputs).
    let at = |factor: f64| exposure::apply(&base, factor as f32).unwrap_or_else(|| base.clone());
    let engine = || engine_at(&tiny_v2(), 32);
    for factor in [0.99 * top / level, top / level / 1000.0] {
        assert_eq!(engine().denoise(&at(factor), None, &mut |_| true).unwrap().exposure, 1.0);
    }
    let (a, b) = (100.0 * top / level, 1000.0 * top / level);
    let bright_a = engine().denoise(&at(a), None, &mut |_| true).unwrap();
    let bright_b = engine().denoise(&at(b), None, &mut |_| true).unwrap();
    for (out, k) in [(&bright_a, a), (&bright_b, b)] {
        let reached = f64::from(out.exposure) * k * level;
        assert!((reached / top - 1.0).abs() < 1e-3, "scaled to level {reached}, not {top}");
    }
    for c in 0..3 {
        let ra: Vec<f32> = bright_a.color[c].iter().map(|v| (f64::from(*v) / a) as f32).collect();
        let rb: Vec<f32> = bright_b.color[c].iter().map(|v| (f64::from(*v) / b) as f32).collect();
        let d = max_rel_diff(&ra, &rb);
        assert!(d <= 1e-4, "color {c}: the two units give results {d} apart");
        // Not the noisy frame scaled back: the networks filtered it.
        let noisy = at(a).color();
        let rn: Vec<f32> = noisy[c].iter().map(|v| (f64::from(*v) / a) as f32).collect();
        assert!(max_rel_diff(&ra, &rn) > 1e-3);
    }
}

#[test]
fn models_report_their_contract_fields() {
    let e = engine_at(&tiny_v2(), 0);
    assert_eq!(e.variants(), vec![Variant::Full, Variant::Nocov]);
    let models = e.models();
    assert_eq!(models.len(), 2);
    for m in &models {
        assert_eq!((m.contract, m.component, m.component_name()), (2, None, "both"));
        assert_eq!((m.kernel_size, m.levels, m.receptive_radius), (5, 3, 27));
        assert!(m.path.ends_with("model.onnx"));
        assert!(m.architecture.starts_with("msnet"), "{}", m.architecture);
    }
    assert_eq!(models[0].features, FeatureSet::Full);
    assert_eq!(models[1].features, FeatureSet::Nocov);
    assert_eq!(e.flops_per_pixel(Variant::Full), Some(9162.0));
}

#[test]
fn inputs_compressed_by_the_engine_give_the_graphs_output() {
    // tiny-v2-engine/full is tiny-v2/full exported without the symlog in its graph: the
    // engine compresses the inputs instead, and the kernels still filter the plain color.
    let engine_form = tiny_v2().with_file_name("tiny-v2-engine");
    let frame = synthetic_frame(90, 70, true);
    for tile in [0, 32] {
        let mut graph = engine_at(&tiny_v2(), tile);
        let mut engine = engine_at(&engine_form, tile);
        assert_eq!(graph.models()[0].input_compression, InputCompression::Graph);
        assert_eq!(engine.models()[0].input_compression, InputCompression::Engine);
        let a = graph.denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
        let b = engine.denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
        for c in 0..3 {
            for (name, x, y) in [
                ("diffuse", &parts(&a).diffuse[c], &parts(&b).diffuse[c]),
                ("specular", &parts(&a).specular[c], &parts(&b).specular[c]),
            ] {
                let d = max_rel_diff(x, y);
                assert!(d <= 1e-5, "tile {tile}, {name} {c}: relative difference {d}");
            }
        }
    }
    // The key decides what the engine feeds: a graph that compresses its inputs itself,
    // marked `engine`, gets them compressed twice and filters differently.
    let tmp = tempfile::tempdir().unwrap();
    let twice = set_meta(&read(&tiny_v2(), "full", "model.onnx"), "mcdenoise.input_compression", "engine");
    write(tmp.path(), "full", "model.onnx", &twice);
    let a = engine_at(&tiny_v2(), 0).denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
    let b = engine_at(tmp.path(), 0).denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
    assert!(max_rel_diff(&parts(&a).diffuse[0], &parts(&b).diffuse[0]) > 1e-3);
    // Without the key, the graph compresses (models exported before it existed).
    let tmp = tempfile::tempdir().unwrap();
    let absent =
        rename(&read(&tiny_v2(), "full", "model.onnx"), "mcdenoise.input_compression", "mcdenoise_input_compression");
    write(tmp.path(), "full", "model.onnx", &absent);
    let e = engine_at(tmp.path(), 0);
    assert_eq!(e.models()[0].input_compression, InputCompression::Graph);
}

#[test]
fn the_specular_pyramid_follows_the_metadata() {
    // tiny-v2 predates `mcdenoise.specular_pyramid`: its specular levels average ln(1 + s)
    // (`log`). Marked `linear`, the same kernels filter levels of ln(1 + the mean of s),
    // which is larger wherever the samples spread (a rendered 8-spp frame): the specular
    // comes out brighter, the diffuse is untouched, and tiles still equal the whole frame.
    let frame = fixture_frame("caustic-spp8.exr");
    let tmp = tempfile::tempdir().unwrap();
    let linear = set_meta(&read(&tiny_v2(), "full", "model.onnx"), "mcdenoise.specular_pyramid", "linear");
    write(tmp.path(), "full", "model.onnx", &linear);
    let mut log = engine_at(&tiny_v2(), 0);
    assert_eq!(log.models()[0].specular_pyramid, SpecularPyramid::Log);
    let a = log.denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
    let mut whole = engine_at(tmp.path(), 0);
    assert_eq!(whole.models()[0].specular_pyramid, SpecularPyramid::Linear);
    let b = whole.denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
    let tiled = engine_at(tmp.path(), 16).denoise(&frame, Some(Variant::Full), &mut |_| true).unwrap();
    let sum = |v: &[f32]| v.iter().map(|x| f64::from(*x)).sum::<f64>();
    for c in 0..3 {
        assert_eq!(parts(&a).diffuse[c], parts(&b).diffuse[c], "diffuse {c}");
        let (sa, sb) = (&parts(&a).specular[c], &parts(&b).specular[c]);
        assert!(max_rel_diff(sa, sb) > 1e-3, "specular {c}: the pyramid made no difference");
        assert!(sum(sb) > sum(sa), "specular {c}: {} is not above {}", sum(sb), sum(sa));
        let d = max_rel_diff(&parts(&tiled).specular[c], sb);
        assert!(d <= 1e-5, "specular {c}: tiles differ from the whole frame by {d}");
    }
}

fn engine_reconstructing(dir: &Path, tile: usize, reconstruction: Reconstruction) -> Engine {
    let mut config = EngineConfig::new(dir);
    (config.tile, config.tile_v2, config.threads, config.reconstruction) = (tile, tile, 2, reconstruction);
    Engine::load(&config).expect("models load")
}

#[test]
fn the_reconstruction_in_the_graph_gives_the_engines_output() {
    // tiny-v2's model-recon.onnx: the same networks with recon_ms's reconstruction in the
    // graph, which a GPU runs there; here ONNX Runtime's CPU provider runs it.
    for cov in [true, false] {
        let frame = synthetic_frame(90, 70, cov);
        for tile in [0, 32] {
            let mut rust = engine_reconstructing(&tiny_v2(), tile, Reconstruction::Engine);
            let mut graph = engine_reconstructing(&tiny_v2(), tile, Reconstruction::Graph);
            assert!(rust.models().iter().all(|m| m.outputs == Outputs::Kernels && m.path.ends_with("model.onnx")));
            assert!(graph
                .models()
                .iter()
                .all(|m| m.outputs == Outputs::Filtered && m.path.ends_with("model-recon.onnx")));
            let a = rust.denoise(&frame, None, &mut |_| true).unwrap();
            let b = graph.denoise(&frame, None, &mut |_| true).unwrap();
            assert_eq!((a.variant, a.tiles), (b.variant, b.tiles));
            for c in 0..3 {
                for (name, x, y) in [
                    ("color", &a.color[c], &b.color[c]),
                    ("diffuse", &parts(&a).diffuse[c], &parts(&b).diffuse[c]),
                    ("specular", &parts(&a).specular[c], &parts(&b).specular[c]),
                ] {
                    let d = max_rel_diff(x, y);
                    assert!(d <= 1e-5, "cov {cov}, tile {tile}, {name} {c}: relative difference {d}");
                }
            }
        }
    }
    // On the CPU, `auto` keeps the engine's reconstruction (its own code is the faster there).
    let auto = engine_reconstructing(&tiny_v2(), 0, Reconstruction::Auto);
    assert!(auto.models().iter().all(|m| m.outputs == Outputs::Kernels));
}

#[test]
fn io_binding_gives_the_same_output() {
    // The bound path places the tensors where a GPU reads them by DMA; here ONNX Runtime's
    // CPU memory. Tiles of 32 on 90×70 give regions of several shapes, so the bound tensors
    // are allocated again between regions and reused where a shape repeats.
    let at = |io_binding: IoBinding, reconstruction: Reconstruction| {
        let mut config = EngineConfig::new(tiny_v2());
        (config.threads, config.tile_v2, config.reconstruction, config.io_binding) =
            (2, 32, reconstruction, io_binding);
        Engine::load(&config).unwrap()
    };
    for reconstruction in [Reconstruction::Engine, Reconstruction::Graph] {
        let (mut bound, mut plain) = (at(IoBinding::On, reconstruction), at(IoBinding::Off, reconstruction));
        for cov in [true, false] {
            let frame = synthetic_frame(90, 70, cov);
            let options = Options { components: true, ..Options::default() };
            let a = bound.denoise_with(&frame, options, &mut |_| true).unwrap();
            let b = plain.denoise_with(&frame, options, &mut |_| true).unwrap();
            assert!(a.tiles >= 9, "{} tiles", a.tiles);
            for c in 0..3 {
                assert!(a.color[c].iter().all(|v| v.is_finite()));
                assert_eq!(a.color[c], b.color[c], "{reconstruction:?}, cov {cov}, color {c}");
                assert_eq!(parts(&a).specular[c], parts(&b).specular[c], "{reconstruction:?}, cov {cov}, specular {c}");
            }
        }
    }
}

#[test]
fn the_half_precision_network_stays_near_the_float_one() {
    // tiny-v2's model-recon-fp16.onnx: the network in float16, its inputs compressed and its
    // reconstruction run in float32. ONNX Runtime's CPU provider runs it here (slowly); a GPU
    // runs it on its tensor cores.
    let at = |precision: Precision, reconstruction: Reconstruction| {
        let mut config = EngineConfig::new(tiny_v2());
        (config.threads, config.tile_v2, config.reconstruction, config.precision) = (2, 32, reconstruction, precision);
        Engine::load(&config)
    };
    let mut half = at(Precision::Fp16, Reconstruction::Auto).unwrap();
    assert!(half.models().iter().all(|m| m.precision == Precision::Fp16
        && m.outputs == Outputs::Filtered
        && m.path.ends_with("model-recon-fp16.onnx")));
    let mut float = at(Precision::Fp32, Reconstruction::Graph).unwrap();
    assert!(float.models().iter().all(|m| m.precision == Precision::Fp32 && m.path.ends_with("model-recon.onnx")));
    for cov in [true, false] {
        let frame = synthetic_frame(90, 70, cov);
        let a = half.denoise(&frame, None, &mut |_| true).unwrap();
        let b = float.denoise(&frame, None, &mut |_| true).unwrap();
        for c in 0..3 {
            assert!(a.color[c].iter().all(|v| v.is_finite()));
            let d = max_rel_diff(&a.color[c], &b.color[c]);
            assert!(d > 0.0 && d <= 2e-2, "cov {cov}, color {c}: relative difference {d}");
        }
    }
    // On the CPU, `auto` stays in float32; fp16 needs its file and the graph's reconstruction.
    let auto = at(Precision::Auto, Reconstruction::Auto).unwrap();
    assert!(auto.models().iter().all(|m| m.precision == Precision::Fp32 && m.path.ends_with("model.onnx")));
    let err = at(Precision::Fp16, Reconstruction::Engine).err().unwrap().to_string();
    assert!(err.contains("--precision fp16 runs the half-precision network"), "{err}");
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "full", "model.onnx", &read(&tiny_v2(), "full", "model.onnx"));
    let mut config = EngineConfig::new(tmp.path());
    (config.threads, config.precision) = (1, Precision::Fp16);
    let err = Engine::load(&config).err().unwrap().to_string();
    assert!(err.contains("--precision fp16 needs model-recon-fp16.onnx beside model.onnx"), "{err}");
    // A float32 graph under the half-precision name is refused.
    write(tmp.path(), "full", "model-recon-fp16.onnx", &read(&tiny_v2(), "full", "model-recon.onnx"));
    let err = Engine::load(&config).err().unwrap().to_string();
    assert!(err.contains("metadata `mcdenoise.precision` is `fp32`, expected `fp16`"), "{err}");
}

#[test]
fn graph_reconstruction_needs_its_file_and_the_right_outputs() {
    let load = |files: &[(&str, Vec<u8>)]| -> String {
        let tmp = tempfile::tempdir().unwrap();
        for (file, bytes) in files {
            write(tmp.path(), "full", file, bytes);
        }
        let mut config = EngineConfig::new(tmp.path());
        (config.threads, config.reconstruction) = (1, Reconstruction::Graph);
        match Engine::load(&config) {
            Ok(_) => panic!("loaded"),
            Err(e) => e.to_string(),
        }
    };
    let kernels = read(&tiny_v2(), "full", "model.onnx");
    let recon = read(&tiny_v2(), "full", "model-recon.onnx");
    let cases = [
        (vec![("model.onnx", kernels.clone())], "--reconstruction graph needs model-recon.onnx beside model.onnx"),
        (
            vec![("model.onnx", kernels.clone()), ("model-recon.onnx", kernels.clone())],
            "model-recon.onnx: metadata `mcdenoise.outputs` is `kernels`, expected `filtered` in this file",
        ),
        (
            vec![("model.onnx", kernels.clone()), ("model-recon.onnx", set_meta(&recon, "mcdenoise.outputs", "both"))],
            "metadata `mcdenoise.outputs` is `both`, expected `kernels` or `filtered`",
        ),
        (
            vec![
                ("model.onnx", kernels.clone()),
                ("model-recon.onnx", set_meta(&recon, "mcdenoise.input_compression", "engine")),
            ],
            "`mcdenoise.outputs` is `filtered` but `mcdenoise.input_compression` is `engine`",
        ),
        (
            vec![
                ("model.onnx", kernels.clone()),
                ("model-recon.onnx", rename(&recon, "diffuse_filtered", "diffuse_filterex")),
            ],
            "graph has no `diffuse_filtered`",
        ),
    ];
    for (files, want) in cases {
        let msg = load(&files);
        assert!(msg.contains(want), "expected {want:?} in: {msg}");
    }
}

fn load_error(dir: &Path) -> String {
    let mut config = EngineConfig::new(dir);
    config.threads = 1;
    match Engine::load(&config) {
        Ok(e) => panic!("loaded a bad model set: {:?}", e.variants()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn any_directory_is_a_variant_and_contracts_mix() {
    let dir = mixed();
    let mut e = engine_at(dir.path(), 32);
    let lin2020 = Variant::parse("lin2020").unwrap();
    assert_eq!(e.variants(), vec![Variant::Full, lin2020, Variant::Nocov]);
    let contracts: Vec<(String, u32)> = e.models().iter().map(|m| (m.variant.to_string(), m.contract)).collect();
    assert_eq!(
        contracts,
        [("full", 2), ("lin2020", 1), ("lin2020", 1), ("nocov", 1), ("nocov", 1)].map(|(v, c)| (v.to_string(), c))
    );

    // Automatic choice: full (v2) with covariance, nocov (v1) without.
    let with_cov = synthetic_frame(40, 36, true);
    let without = synthetic_frame(40, 36, false);
    assert_eq!(e.denoise(&with_cov, None, &mut |_| true).unwrap().variant, Variant::Full);
    assert_eq!(e.denoise(&without, None, &mut |_| true).unwrap().variant, Variant::Nocov);

    // Named: lin2020 takes the full features, so it needs covariance.
    let out = e.denoise(&with_cov, Some(lin2020), &mut |_| true).unwrap();
    assert_eq!(out.variant, lin2020);
    // The same networks as the v1 `full` pair give the same result.
    let v1 = engine(32).denoise(&with_cov, Some(Variant::Full), &mut |_| true).unwrap();
    assert!(max_rel_diff(&out.color[1], &v1.color[1]) <= 1e-6);
    let err = e.denoise(&without, Some(lin2020), &mut |_| true).err().unwrap().to_string();
    assert!(err.contains("the `lin2020` model needs a `covariance` channel"), "{err}");
    let err = e.denoise(&with_cov, Variant::parse("oidn"), &mut |_| true).err().unwrap().to_string();
    assert!(err.contains("no `oidn` model is loaded (loaded: full, lin2020, nocov)"), "{err}");
}

/// Engines of `dir` that load each variant on first use, tiles of 32, 2 threads.
fn on_demand(dir: &Path) -> EngineConfig {
    let mut config = EngineConfig::new(dir);
    (config.tile, config.tile_v2, config.threads) = (32, 32, 2);
    config.loading = ModelLoading::OnDemand;
    config
}

/// `ModelLoading::OnDemand` (what `mcdenoise run` uses): the variants are found at load and
/// each one's networks created when a frame first needs them, with the same results as a
/// whole load; a broken variant that no frame uses does not stop the others.
#[test]
fn on_demand_loading_creates_only_the_networks_a_frame_uses() {
    let dir = mixed();
    let config = on_demand(dir.path());
    let mut lazy = Engine::load(&config).unwrap();
    let lin2020 = Variant::parse("lin2020").unwrap();
    assert_eq!(lazy.variants(), vec![Variant::Full, lin2020, Variant::Nocov]);
    assert!(lazy.models().is_empty(), "nothing created before a frame");
    let loaded = |e: &Engine| e.models().iter().map(|m| m.variant.to_string()).collect::<Vec<_>>();

    let with_cov = synthetic_frame(40, 36, true);
    let out = lazy.denoise(&with_cov, None, &mut |_| true).unwrap();
    assert_eq!((out.variant, loaded(&lazy)), (Variant::Full, vec!["full".to_string()]));
    let eager = engine_at(dir.path(), 32).denoise(&with_cov, None, &mut |_| true).unwrap();
    assert_eq!(out.color, eager.color);
    lazy.denoise(&with_cov, None, &mut |_| true).unwrap();
    assert_eq!(loaded(&lazy), ["full"], "loaded once");
    let out = lazy.denoise(&synthetic_frame(40, 36, false), None, &mut |_| true).unwrap();
    assert_eq!((out.variant, loaded(&lazy)), (Variant::Nocov, ["full", "nocov", "nocov"].map(String::from).to_vec()));
    let err = lazy.denoise(&with_cov, Variant::parse("oidn"), &mut |_| true).err().unwrap().to_string();
    assert!(err.contains("no `oidn` model is loaded (loaded: full, lin2020, nocov)"), "{err}");

    // A variant whose file is not a model: the eager load refuses the set, the on-demand one
    // serves the others and names the broken file when that variant is asked for.
    std::fs::write(dir.path().join("lin2020/diffuse.onnx"), b"not an onnx file").unwrap();
    let eager_err = load_error(dir.path());
    assert!(eager_err.contains("lin2020"), "{eager_err}");
    let mut lazy = Engine::load(&config).unwrap();
    assert_eq!(lazy.denoise(&with_cov, None, &mut |_| true).unwrap().variant, Variant::Full);
    let err = lazy.denoise(&with_cov, Some(lin2020), &mut |_| true).err().unwrap().to_string();
    assert!(err.contains("lin2020") && err.contains("diffuse.onnx"), "{err}");
    let again = lazy.denoise(&with_cov, Some(lin2020), &mut |_| true).err().unwrap().to_string();
    assert_eq!(again, err, "asked again, the same error");
}

/// `Denoiser::prepare` (what the pipeline calls while a frame decodes, from its header's
/// kind) loads the variant the frame will be denoised with, and nothing else; a variant
/// that cannot load is left for the denoising to report.
#[test]
fn prepare_loads_the_variant_a_frame_of_that_kind_needs() {
    let dir = mixed();
    let config = on_demand(dir.path());
    let loaded = |e: &Engine| e.models().iter().map(|m| m.variant.to_string()).collect::<Vec<_>>();
    let mut lazy = Engine::load(&config).unwrap();
    assert!(lazy.loads_on_demand());
    let without_cov = synthetic_frame(40, 36, false);
    lazy.prepare(None, without_cov.kind());
    assert_eq!(loaded(&lazy), ["nocov", "nocov"], "one network per component of the v1 variant");
    let with_cov = synthetic_frame(40, 36, true);
    lazy.prepare(None, with_cov.kind());
    assert_eq!(loaded(&lazy), ["nocov", "nocov", "full"]);
    let before = lazy.loaded_on_demand();
    assert_eq!(lazy.denoise(&with_cov, None, &mut |_| true).unwrap().variant, Variant::Full);
    assert_eq!(lazy.loaded_on_demand(), before, "nothing loaded again");
    // A named variant is loaded whatever the frame's kind; every variant loaded, nothing left.
    let lin2020 = Variant::parse("lin2020").unwrap();
    lazy.prepare(Some(lin2020), without_cov.kind());
    assert!(loaded(&lazy).contains(&"lin2020".to_string()));
    assert!(!lazy.loads_on_demand());

    // A broken variant: prepare says nothing, the denoising names the file.
    std::fs::write(dir.path().join("lin2020/diffuse.onnx"), b"not an onnx file").unwrap();
    let mut lazy = Engine::load(&config).unwrap();
    lazy.prepare(Some(lin2020), with_cov.kind());
    assert!(lazy.models().is_empty());
    let err = lazy.denoise(&with_cov, Some(lin2020), &mut |_| true).err().unwrap().to_string();
    assert!(err.contains("lin2020") && err.contains("diffuse.onnx"), "{err}");
}

#[test]
fn without_full_or_nocov_a_variant_must_be_named() {
    let tmp = tempfile::tempdir().unwrap();
    write(
        tmp.path(),
        "wide",
        "model.onnx",
        &set_meta(&read(&tiny_v2(), "full", "model.onnx"), "mcdenoise.variant", "wide"),
    );
    let mut e = engine_at(tmp.path(), 0);
    let err = e.denoise(&synthetic_frame(20, 20, true), None, &mut |_| true).err().unwrap().to_string();
    assert!(err.contains("no `full` or `nocov` model is loaded (loaded: wide); name a variant"), "{err}");
    assert!(e.denoise(&synthetic_frame(20, 20, true), Variant::parse("wide"), &mut |_| true).is_ok());
}

#[test]
fn frames_without_the_split_go_to_the_beauty_variant() {
    // `beauty`: the tiny `nocov` network under another name, so its results can be compared.
    let tmp = tempfile::tempdir().unwrap();
    for v in ["full", "nocov"] {
        write(tmp.path(), v, "model.onnx", &read(&tiny_v2(), v, "model.onnx"));
    }
    let nocov = read(&tiny_v2(), "nocov", "model.onnx");
    write(tmp.path(), "beauty", "model.onnx", &set_meta(&nocov, "mcdenoise.variant", "beauty"));
    // First without the albedo prefilter, which a beauty-only frame (no albedo variance)
    // never gets.
    let mut config = EngineConfig::new(tmp.path());
    (config.tile, config.tile_v2, config.threads) = (0, 0, 2);
    config.albedo_prefilter = AlbedoPrefilter::Off;
    let mut e = Engine::load(&config).unwrap();
    assert_eq!(e.variants(), vec![Variant::Beauty, Variant::Full, Variant::Nocov]);

    let split = synthetic_frame(40, 36, true);
    let beauty = split.to_beauty();
    let auto = e.denoise(&beauty, None, &mut |_| true).unwrap();
    assert_eq!(auto.variant, Variant::Beauty);
    assert!(parts(&auto).specular.iter().flatten().all(|v| *v == 0.0));
    assert_eq!(e.denoise(&split, None, &mut |_| true).unwrap().variant, Variant::Full);
    // Named for a frame with the split: the engine hands the network the same inputs.
    let named = e.denoise(&split, Some(Variant::Beauty), &mut |_| true).unwrap();
    let direct = e.denoise(&beauty, Some(Variant::Nocov), &mut |_| true).unwrap();
    for c in 0..3 {
        assert_eq!(named.color[c], auto.color[c]);
        assert_eq!(named.color[c], direct.color[c]);
    }
    // With the albedo prefilter (the default), those of the beauty-only frame of the
    // prefiltered split.
    let mut on = engine_at(tmp.path(), 0);
    let named = on.denoise(&split, Some(Variant::Beauty), &mut |_| true).unwrap();
    let prefiltered = albedo::prefilter(&split, AlbedoPrefilter::On).expect("the frame has an albedo variance");
    let direct = on.denoise(&prefiltered.to_beauty(), Some(Variant::Nocov), &mut |_| true).unwrap();
    for c in 0..3 {
        assert_eq!(named.color[c], direct.color[c]);
    }
    assert_ne!(named.color[0], auto.color[0], "the prefilter changed the albedo");
    // Without a `beauty` model, `nocov` takes such frames.
    let mut e = engine_at(&tiny_v2(), 0);
    assert_eq!(e.denoise(&beauty, None, &mut |_| true).unwrap().variant, Variant::Nocov);
}

/// Loads a directory holding `full/model.onnx` edited by `edit`; returns the error.
fn v2_error(edit: impl Fn(Vec<u8>) -> Vec<u8>) -> String {
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "full", "model.onnx", &edit(read(&tiny_v2(), "full", "model.onnx")));
    load_error(tmp.path())
}

#[test]
fn bad_contract_v2_models_are_refused_with_the_file_and_field_named() {
    let cases: Vec<(Box<dyn Fn(Vec<u8>) -> Vec<u8>>, &str)> = vec![
        (
            Box::new(|b| set_meta(&b, "mcdenoise.contract", "1")),
            "`mcdenoise.contract` is `1`, expected `2` (a contract-1 model is two files, diffuse.onnx and specular.onnx)",
        ),
        (Box::new(|b| rename(&b, "kernel_2", "kernel_7")), "graph has no `kernel_2`"),
        (Box::new(|b| rename(&b, "blend_1", "blend_9")), "graph has no `blend_1`"),
        (
            Box::new(|b| set_meta(&b, "mcdenoise.size_multiple", "8")),
            "`mcdenoise.size_multiple` is `8`, expected `4` (2^(levels − 1), levels = 3)",
        ),
        (
            Box::new(|b| set_meta(&set_meta(&b, "mcdenoise.levels", "2"), "mcdenoise.size_multiple", "2")),
            "graph has an unexpected output `kernel_2`",
        ),
        (
            Box::new(|b| set_meta(&set_meta(&b, "mcdenoise.levels", "4"), "mcdenoise.size_multiple", "8")),
            "`mcdenoise.levels` = 4 expects outputs kernel_0 … kernel_3 and blend_0 … blend_2",
        ),
        (Box::new(|b| set_meta(&b, "mcdenoise.kernel_size", "4")), "`mcdenoise.kernel_size` is 4, expected an odd number"),
        (Box::new(|b| set_meta(&b, "mcdenoise.kernel_size", "3")), "`kernel_0` has 50 channels, expected 18"),
        (Box::new(|b| set_meta(&b, "mcdenoise.levels", "many")), "`mcdenoise.levels` is not a number"),
        (Box::new(|b| rename(&b, "mcdenoise.levels", "mcdenoise_levels")), "metadata `mcdenoise.levels` is missing"),
        (Box::new(|b| rename(&b, "mcdenoise.architecture", "mcdenoise_architecture")), "`mcdenoise.architecture` is missing"),
        (Box::new(|b| set_meta(&b, "mcdenoise.features", "normal.R")), "`mcdenoise.features` is `normal.R`"),
        (Box::new(|b| rename(&b, "specular", "specul_r")), "graph has no `specular`"),
        (
            Box::new(|b| set_meta(&b, "mcdenoise.input_compression", "gpu")),
            "metadata `mcdenoise.input_compression` is `gpu`, expected `graph` or `engine`",
        ),
        (
            Box::new(|b| set_meta(&b, "mcdenoise.specular_pyramid", "median")),
            "metadata `mcdenoise.specular_pyramid` is `median`, expected `log` or `linear`",
        ),
    ];
    for (edit, want) in cases {
        let msg = v2_error(edit);
        assert!(msg.contains("full/model.onnx") && msg.contains(want), "expected {want:?} in: {msg}");
    }
}

#[test]
fn misplaced_or_mixed_files_are_refused() {
    // A full model in nocov/.
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "nocov", "model.onnx", &read(&tiny_v2(), "full", "model.onnx"));
    let msg = load_error(tmp.path());
    assert!(
        msg.contains("nocov/model.onnx") && msg.contains("`mcdenoise.variant` is `full`, expected `nocov`"),
        "{msg}"
    );

    // A contract-2 graph named diffuse.onnx.
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "full", "diffuse.onnx", &read(&tiny_v2(), "full", "model.onnx"));
    write(tmp.path(), "full", "specular.onnx", &read(&tiny_models(), "full", "specular.onnx"));
    let msg = load_error(tmp.path());
    assert!(
        msg.contains("full/diffuse.onnx") && msg.contains("is `2`, expected `1` (a contract-2 model is one file"),
        "{msg}"
    );

    // Both layouts in one directory.
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "full", "model.onnx", &read(&tiny_v2(), "full", "model.onnx"));
    write(tmp.path(), "full", "diffuse.onnx", &read(&tiny_models(), "full", "diffuse.onnx"));
    assert!(load_error(tmp.path()).contains("holds both model.onnx"));

    // A v1 pair whose components take different features.
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "full", "diffuse.onnx", &read(&tiny_models(), "full", "diffuse.onnx"));
    write(
        tmp.path(),
        "full",
        "specular.onnx",
        &set_meta(&read(&tiny_models(), "nocov", "specular.onnx"), "mcdenoise.variant", "full"),
    );
    let msg = load_error(tmp.path());
    assert!(msg.contains("diffuse.onnx takes the `full` features but specular.onnx the `nocov` ones"), "{msg}");

    // A directory name that cannot be a variant.
    let tmp = tempfile::tempdir().unwrap();
    write(tmp.path(), "my model", "model.onnx", &read(&tiny_v2(), "full", "model.onnx"));
    assert!(load_error(tmp.path()).contains("`my model` is not a valid variant name"));
}
