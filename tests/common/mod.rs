//! Helpers shared by the integration tests: synthetic frames and EXR files.
#![allow(dead_code)]

use std::path::PathBuf;

use exr::prelude::*;
use mcdenoise::engine::{synthetic_planes, Engine, EngineConfig};
use mcdenoise::frame::{Frame, NamedPlanes};

/// A part of a multi-part file: name, size, channels.
pub type Part<'a> = (&'a str, (usize, usize), NamedPlanes);

pub fn tiny_models() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/models/tiny")
}

pub fn engine(tile: usize) -> Engine {
    let mut config = EngineConfig::new(tiny_models());
    config.tile = tile;
    config.threads = 2;
    Engine::load(&config).expect("tiny models load (is the ONNX Runtime library installed? run scripts/setup)")
}

/// The canonical channels of a synthetic frame, as named planes.
pub fn named_planes(w: usize, h: usize, with_covariance: bool) -> Vec<(String, Vec<f32>)> {
    synthetic_planes(w, h, with_covariance)
}

pub use mcdenoise::frame::SampleType as Sample;

fn channel(name: &str, data: &[f32], sample: Sample) -> AnyChannel<FlatSamples> {
    let samples = match sample {
        Sample::F32 => FlatSamples::F32(data.to_vec()),
        Sample::F16 => FlatSamples::F16(data.iter().map(|v| f16::from_f32(*v)).collect()),
    };
    AnyChannel::new(name, samples)
}

/// A single-part EXR holding `planes`.
pub fn exr_single(w: usize, h: usize, planes: &[(String, Vec<f32>)], sample: Sample) -> Vec<u8> {
    let named = planes.iter().map(|(n, d)| (n.as_str(), d.as_slice()));
    mcdenoise::frame::write_planes(w, h, named, sample, Encoding::FAST_LOSSLESS).unwrap()
}

/// A multi-part EXR: one part per prefix (`diffuse.R` goes to part `diffuse` as channel
/// `R`), each part of its own size.
pub fn exr_multi(parts: &[Part<'_>], sample: Sample) -> Vec<u8> {
    let layers: Vec<_> = parts
        .iter()
        .map(|(name, size, planes)| {
            let list: SmallVec<[AnyChannel<FlatSamples>; 4]> =
                planes.iter().map(|(n, d)| channel(n, d, sample)).collect();
            Layer::new(*size, LayerAttributes::named(*name), Encoding::FAST_LOSSLESS, AnyChannels::sort(list))
        })
        .collect();
    let image = Image::from_layers(ImageAttributes::new(IntegerBounds::from_dimensions(parts[0].1)), layers);
    let mut out = std::io::Cursor::new(Vec::new());
    image.write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// Splits canonical names into parts by their prefix (`diffuse.R` → part `diffuse`, channel
/// `R`; names without a dot go to part `main`).
pub fn by_part(planes: &[(String, Vec<f32>)]) -> Vec<(String, NamedPlanes)> {
    let mut parts: Vec<(String, NamedPlanes)> = Vec::new();
    for (name, data) in planes {
        let (part, ch) = match name.split_once('.') {
            Some((p, c)) => (p.to_string(), c.to_string()),
            None => (name.clone(), "V".to_string()),
        };
        match parts.iter_mut().find(|(p, _)| *p == part) {
            Some((_, list)) => list.push((ch, data.clone())),
            None => parts.push((part, vec![(ch, data.clone())])),
        }
    }
    parts
}

pub fn frame_of(bytes: &[u8]) -> Frame {
    Frame::from_exr_bytes(bytes, &Default::default()).expect("valid frame")
}

pub fn max_rel_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
    a.iter().zip(b).map(|(x, y)| (x - y).abs() / scale).fold(0f32, f32::max)
}

/// A frame as Blender Cycles writes it: one part per pass `ViewLayer.<pass>`, no diffuse or
/// specular buffer, no variance, background depth 1e10; only the passes `keep` accepts.
pub fn cycles_frame(w: usize, h: usize, keep: impl Fn(&str) -> bool) -> (Vec<u8>, Vec<(String, Vec<f32>)>) {
    #[allow(non_snake_case)]
    let (W, H) = (w, h);
    let planes = named_planes(W, H, false);
    let get = |n: &str| planes.iter().find(|(k, _)| k == n).unwrap().1.clone();
    let mut parts: Vec<(String, NamedPlanes)> = Vec::new();
    let mut pass = |name: &str, chans: &[&str], data: Vec<Vec<f32>>| {
        if !keep(name) {
            return;
        }
        let list = chans.iter().zip(data).map(|(c, d)| (c.to_string(), d)).collect();
        parts.push((format!("ViewLayer.{name}"), list));
    };
    let rgb = ["R", "G", "B"];
    let (d, s, a): (Vec<_>, Vec<_>, Vec<_>) = (
        rgb.iter().map(|c| get(&format!("diffuse.{c}"))).collect(),
        rgb.iter().map(|c| get(&format!("specular.{c}"))).collect(),
        rgb.iter().map(|c| get(&format!("albedo.{c}"))).collect(),
    );
    let irradiance = |c: usize, share: f32| d[c].iter().zip(&a[c]).map(|(d, a)| share * d / a).collect::<Vec<f32>>();
    pass("Combined", &["R", "G", "B", "A"], {
        let mut v: Vec<Vec<f32>> = (0..3).map(|c| d[c].iter().zip(&s[c]).map(|(x, y)| x + y).collect()).collect();
        v.push(vec![1.0; W * H]);
        v
    });
    pass("Diffuse Direct", &rgb, (0..3).map(|c| irradiance(c, 0.7)).collect());
    pass("Diffuse Indirect", &rgb, (0..3).map(|c| irradiance(c, 0.3)).collect());
    pass("Diffuse Color", &rgb, a.clone());
    pass("Denoising Albedo", &rgb, a.clone());
    pass("Denoising Normal", &["X", "Y", "Z"], rgb.iter().map(|c| get(&format!("normal.{c}"))).collect());
    let mut depth = get("depth.Z");
    depth[0] = 1e10;
    pass("Depth", &["Z"], vec![depth]);
    let spec: Vec<_> = parts.iter().map(|(p, l)| (p.as_str(), (W, H), l.clone())).collect();
    (exr_multi(&spec, Sample::F32), planes)
}

