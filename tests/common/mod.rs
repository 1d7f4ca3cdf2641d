//! Helpers shared by the integration tests: synthetic frames and EXR files.
#![allow(dead_code)]

use std::path::PathBuf;

use exr::prelude::*;
use mcdenoise::engine::{synthetic_planes, Components, Denoised, Engine, EngineConfig};
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

/// The diffuse and specular of a result denoised with them ([`Engine::denoise`] asks for them).
pub fn parts(out: &Denoised) -> &Components {
    out.components.as_ref().expect("denoised without its components")
}

/// A committed fixture frame (tests/fixtures/frames) as the engine reads it: a reference
/// (`*-ref.exr`) with its color alone, a noisy frame with every buffer.
pub fn fixture_frame(name: &str) -> Frame {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/frames").join(name);
    let bytes = std::fs::read(path).unwrap();
    if name.contains("-ref") {
        Frame::reference_from_exr_bytes(&bytes, &Default::default()).unwrap()
    } else {
        Frame::from_exr_bytes(&bytes, &Default::default()).unwrap()
    }
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

/// A committed fixture frame (tests/fixtures/frames): size, channels as f32, and the own
/// attributes of its header.
pub struct Fixture {
    pub width: usize,
    pub height: usize,
    pub planes: NamedPlanes,
    pub attributes: LayerAttributes,
}

pub fn fixture(name: &str) -> Fixture {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/frames").join(name);
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(&path)
        .unwrap_or_else(|e| panic!("fixture {name}: {e}"));
    let layer = image.layer_data;
    let planes = layer
        .channel_data
        .list
        .into_iter()
        .map(|c| {
            let plane = match c.sample_data {
                FlatSamples::F32(v) => v,
                FlatSamples::F16(v) => v.into_iter().map(f16::to_f32).collect(),
                FlatSamples::U32(v) => v.into_iter().map(|x| x as f32).collect(),
            };
            (c.name.to_string(), plane)
        })
        .collect();
    Fixture { width: layer.size.0, height: layer.size.1, planes, attributes: layer.attributes }
}

/// `index` reflected into `0..len` (…, 2, 1, 0, 1, 2, …, len−1, len−2, …).
fn reflect(index: i64, len: usize) -> usize {
    let period = 2 * (len as i64 - 1).max(1);
    let m = index.rem_euclid(period);
    (if m < len as i64 { m } else { period - m }) as usize
}

/// A `w`×`h` window of the planes of a `src_w`×`src_h` image, starting at pixel `(x0, y0)`
/// of it, mirrored at its borders wherever the window reaches beyond them: windows of one
/// mirrored image, whatever their position and size.
pub fn window(planes: &[(String, Vec<f32>)], src: (usize, usize), x0: i64, y0: i64, w: usize, h: usize) -> NamedPlanes {
    let (sw, sh) = src;
    planes
        .iter()
        .map(|(name, data)| {
            let mut out = Vec::with_capacity(w * h);
            for y in 0..h {
                let row = reflect(y0 + y as i64, sh) * sw;
                out.extend((0..w).map(|x| data[row + reflect(x0 + x as i64, sw)]));
            }
            (name.clone(), out)
        })
        .collect()
}

/// Where a test frame lies, and what its header says.
#[derive(Clone)]
pub struct Placement {
    /// The data window's top-left corner.
    pub origin: (i32, i32),
    pub display: IntegerBounds,
    pub pixel_aspect: f32,
    /// The part's own attributes (the origin is set from `origin`).
    pub attributes: LayerAttributes,
}

impl Placement {
    /// At (0, 0), displayed whole, square pixels, no attributes.
    pub fn plain(w: usize, h: usize) -> Placement {
        Placement {
            origin: (0, 0),
            display: IntegerBounds::from_dimensions((w, h)),
            pixel_aspect: 1.0,
            attributes: LayerAttributes::default(),
        }
    }
}

/// A single-part EXR of `w`×`h` placed as `placement` says, holding `channels` in their
/// own sample types.
pub fn exr_placed(w: usize, h: usize, placement: &Placement, channels: Vec<AnyChannel<FlatSamples>>) -> Vec<u8> {
    let mut attributes = placement.attributes.clone();
    attributes.layer_position = Vec2(placement.origin.0, placement.origin.1);
    let mut image_attributes = ImageAttributes::new(placement.display);
    image_attributes.pixel_aspect = placement.pixel_aspect;
    let layer = Layer::new((w, h), attributes, Encoding::FAST_LOSSLESS, AnyChannels::sort(channels.into()));
    let mut out = std::io::Cursor::new(Vec::new());
    Image::new(image_attributes, layer).write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// f32 channels of `planes`.
pub fn f32_channels(planes: &[(String, Vec<f32>)]) -> Vec<AnyChannel<FlatSamples>> {
    planes.iter().map(|(n, d)| AnyChannel::new(n.as_str(), FlatSamples::F32(d.clone()))).collect()
}

/// Every layer of an EXR file, all channels and attributes.
pub fn read_exr(bytes: &[u8]) -> Image<Layers<AnyChannels<FlatSamples>>> {
    read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .expect("a readable EXR")
}

/// A channel's samples as comparable bits: the sample type and each sample's bit pattern
/// (NaNs included).
pub fn bits(samples: &FlatSamples) -> (&'static str, Vec<u32>) {
    match samples {
        FlatSamples::F16(v) => ("f16", v.iter().map(|x| u32::from(x.to_bits())).collect()),
        FlatSamples::F32(v) => ("f32", v.iter().map(|x| x.to_bits()).collect()),
        FlatSamples::U32(v) => ("u32", v.clone()),
    }
}

/// The own attributes of a renderer's header: a camera matrix, the software, custom ones.
pub fn renderer_attributes() -> LayerAttributes {
    let mut a = LayerAttributes {
        world_to_camera: Some([1.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0, 3.0, -4.0, 5.0, 1.0]),
        software_name: Some(Text::from("Test renderer 1.0")),
        ..LayerAttributes::default()
    };
    a.other.insert(Text::from("renderer/scene"), AttributeValue::Text(Text::from("cornell")));
    a.other.insert(Text::from("renderer/spp"), AttributeValue::I32(8));
    a.other.insert(Text::from("camera/fov"), AttributeValue::F32(39.5));
    a
}

/// The AOVs [`overscan_frame`] adds beside the fixture's channels.
pub const EXTRA_CHANNELS: [&str; 3] = ["A", "crypto00.R", "objectId"];

/// The fixture `cornell-spp8.exr` as a renderer writes it with overscan: the `w`×`h`
/// window from pixel `(x0, y0)` of the fixture mirrored at its borders (see [`window`]),
/// placed as `placement` says, with the fixture's and [`renderer_attributes`]' attributes,
/// and the [`EXTRA_CHANNELS`]: an alpha and a Cryptomatte-like AOV in half precision and a
/// u32 ID, functions of the position in the mirrored image, so that two windows agree where
/// they overlap.
pub fn overscan_frame(x0: i64, y0: i64, w: usize, h: usize, placement: &Placement) -> Vec<u8> {
    let fx = fixture("cornell-spp8.exr");
    let mut channels = f32_channels(&window(&fx.planes, (fx.width, fx.height), x0, y0, w, h));
    let at = |f: &dyn Fn(i64, i64) -> f32| -> Vec<f32> {
        (0..w * h).map(|i| f(x0 + (i % w) as i64, y0 + (i / w) as i64)).collect()
    };
    let half = |v: Vec<f32>| FlatSamples::F16(v.into_iter().map(f16::from_f32).collect());
    channels.push(AnyChannel::new("A", half(at(&|x, y| ((x * 7 + y * 3).rem_euclid(11)) as f32 / 10.0))));
    channels.push(AnyChannel::new("crypto00.R", half(at(&|x, y| (x - 2 * y) as f32 * 0.125))));
    // IDs above 2^24, which f32 cannot hold exactly.
    let ids = (0..w * h).map(|i| {
        let (x, y) = (x0 + (i % w) as i64, y0 + (i / w) as i64);
        (x + 1000 * y).rem_euclid(1 << 20) as u32 * 3 + 16_777_217
    });
    channels.push(AnyChannel::new("objectId", FlatSamples::U32(ids.collect())));
    let mut attributes = renderer_attributes();
    attributes.other.extend(fx.attributes.other);
    let placement = Placement { attributes, ..placement.clone() };
    exr_placed(w, h, &placement, channels)
}

/// Checks that `result` lies where `input` does (data window, display window, pixel
/// aspect), has its attributes and the denoiser's, and carries every input channel but
/// the beauty `R,G,B` bit for bit (the alpha included; `replaced` names the channels a
/// denoised layer replaces); returns the result.
pub fn check_carried(input: &[u8], result: &[u8], replaced: &[&str]) -> Image<Layers<AnyChannels<FlatSamples>>> {
    let (input, result) = (read_exr(input), read_exr(result));
    assert_eq!(result.layer_data.len(), 1, "a single-part result");
    let (inp, out) = (&input.layer_data[0], &result.layer_data[0]);
    assert_eq!(out.encoding, mcdenoise::frame::RESULT_ENCODING, "results are PIZ-compressed scan lines");
    assert_eq!(out.attributes.layer_position, inp.attributes.layer_position, "data window origin");
    assert_eq!(out.size, inp.size, "data window size");
    assert_eq!(result.attributes.display_window, input.attributes.display_window);
    assert_eq!(result.attributes.pixel_aspect, input.attributes.pixel_aspect);
    assert_eq!(out.attributes.world_to_camera, inp.attributes.world_to_camera);
    assert_eq!(out.attributes.software_name, inp.attributes.software_name);
    for (name, value) in &inp.attributes.other {
        assert_eq!(out.attributes.other.get(name), Some(value), "attribute {name}");
    }
    let text = |name: &str| match out.attributes.other.get(&Text::from(name)) {
        Some(AttributeValue::Text(t)) => t.to_string(),
        other => panic!("attribute {name}: {other:?}"),
    };
    assert_eq!(text("mcdenoise/version"), env!("CARGO_PKG_VERSION"));
    assert!(["full", "nocov"].contains(&text("mcdenoise/variant").as_str()));
    assert!(!text("mcdenoise/model").is_empty() && text("mcdenoise/model_sha256").len() >= 64);
    let got: std::collections::BTreeMap<String, &FlatSamples> =
        out.channel_data.list.iter().map(|c| (c.name.to_string(), &c.sample_data)).collect();
    for c in &inp.channel_data.list {
        let name = c.name.to_string();
        if ["R", "G", "B"].contains(&name.as_str()) || replaced.contains(&name.as_str()) {
            assert!(got.get(name.as_str()).is_some_and(|s| bits(s) != bits(&c.sample_data)), "{name} is denoised");
            continue;
        }
        let carried = got.get(name.as_str()).unwrap_or_else(|| panic!("{name} is not carried"));
        assert!(bits(carried) == bits(&c.sample_data), "{name} changed");
    }
    result
}

/// A channel of a single-part image.
pub fn channel_of<'a>(image: &'a Image<Layers<AnyChannels<FlatSamples>>>, name: &str) -> &'a AnyChannel<FlatSamples> {
    image.layer_data[0]
        .channel_data
        .list
        .iter()
        .find(|c| c.name == *name)
        .unwrap_or_else(|| panic!("no channel {name}"))
}

/// Samples of a channel of a single-part image as f32.
pub fn samples_of(image: &Image<Layers<AnyChannels<FlatSamples>>>, name: &str) -> Vec<f32> {
    match &channel_of(image, name).sample_data {
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::U32(v) => v.iter().map(|x| *x as f32).collect(),
    }
}

/// The channel names of a single-part image, in file order.
pub fn channel_names(image: &Image<Layers<AnyChannels<FlatSamples>>>) -> Vec<String> {
    image.layer_data[0].channel_data.list.iter().map(|c| c.name.to_string()).collect()
}
