//! Reading frames: EXR round trips in every supported form, aliases, and one specific error
//! per kind of bad input.

use crate::common;

use common::*;
use mcdenoise::frame::{
    read_header, write_exr, Buffer, ChannelMaps, Frame, FrameError, FrameKind, Limits, OutputLayer, PlaneRef,
};

const W: usize = 19;
const H: usize = 13;

/// Checks the frame's diffuse, normal, depth and covariance against the planes it was read
/// from, within `tolerance` (relative to each plane's largest magnitude); the buffers kept as
/// f16 within f16's rounding as well (2⁻¹¹ of a sample).
fn assert_same_as_planes(frame: &Frame, planes: &[(String, Vec<f32>)], tolerance: f32) {
    let expect = |name: &str| planes.iter().find(|(n, _)| n == name).map(|(_, d)| d.clone()).unwrap();
    let half = tolerance.max(2f32.powi(-11));
    for (c, name) in ["diffuse.R", "diffuse.G", "diffuse.B"].iter().enumerate() {
        assert!(max_rel_diff(frame.f32_plane(Buffer::Diffuse, c), &expect(name)) <= tolerance, "{name}");
    }
    for (c, name) in ["normal.R", "normal.G", "normal.B"].iter().enumerate() {
        assert!(max_rel_diff(&frame.plane(Buffer::Normal, c).to_vec(), &expect(name)) <= half, "{name}");
    }
    assert!(max_rel_diff(frame.f32_plane(Buffer::Depth, 0), &expect("depth.Z")) <= tolerance);
    assert!(max_rel_diff(&frame.plane(Buffer::Covariance, 0).to_vec(), &expect("covariance")) <= half);
}

#[test]
fn single_part_f32_round_trip_is_exact() {
    let planes = named_planes(W, H, true);
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
    assert_eq!((frame.width, frame.height), (W, H));
    assert_same_as_planes(&frame, &planes, 0.0);
    assert_eq!(frame.sanitized.total, 0);
}

#[test]
fn single_part_f16_round_trip_is_within_half_precision() {
    let planes = named_planes(W, H, true);
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F16));
    assert_same_as_planes(&frame, &planes, 1e-3);
}

#[test]
fn multi_part_round_trip_prefixes_part_names() {
    let planes = named_planes(W, H, true);
    let parts = by_part(&planes);
    let spec: Vec<_> = parts.iter().map(|(p, l)| (p.as_str(), (W, H), l.clone())).collect();
    let bytes = exr_multi(&spec, Sample::F32);
    let frame = frame_of(&bytes);
    // Multi-part splits `covariance` into part `covariance`, channel `V`: alias `covariance.V`.
    assert!(frame.has(Buffer::Covariance));
    assert_same_as_planes(&frame, &planes, 0.0);
}

#[test]
fn aliases_xyz_normals_and_three_channel_variances() {
    let mut planes = named_planes(W, H, false);
    for (name, _) in planes.iter_mut() {
        *name = name.replace("normal.R", "normal.X").replace("normal.G", "normal.Y").replace("normal.B", "normal.Z");
    }
    let var = planes.iter().position(|(n, _)| n == "diffuseVariance.Z").unwrap();
    let (_, v) = planes.remove(var);
    for ch in ["R", "G", "B"] {
        planes.push((format!("diffuseVariance.{ch}"), v.clone()));
    }
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
    assert_eq!(frame.planes(Buffer::DiffuseVariance).len(), 3);
    assert_eq!(frame.planes(Buffer::Normal).len(), 3);
    assert!(!frame.has(Buffer::Covariance));
}

#[test]
fn result_exr_round_trip() {
    let r: Vec<f32> = (0..W * H).map(|i| i as f32 * 0.5).collect();
    let g: Vec<f32> = r.iter().map(|v| v + 1.0).collect();
    let b: Vec<f32> = r.iter().map(|v| -v).collect();
    let bytes = write_exr(
        W,
        H,
        &[OutputLayer { prefix: "", planes: [&r, &g, &b] }, OutputLayer { prefix: "diffuse", planes: [&g, &b, &r] }],
    )
    .unwrap();
    assert_eq!(common::read_exr(&bytes).layer_data[0].encoding.compression, exr::prelude::Compression::PIZ);
    let frame = Frame::reference_from_exr_bytes(&bytes, &Limits::default()).unwrap();
    assert_eq!(frame.f32_plane(Buffer::Color, 0), &r[..]);
    assert_eq!(frame.f32_plane(Buffer::Color, 2), &b[..]);
    assert_eq!(frame.f32_plane(Buffer::Diffuse, 1), &b[..]);
}

#[test]
fn missing_channels_are_listed() {
    let planes: Vec<_> =
        named_planes(W, H, false).into_iter().filter(|(n, _)| !n.starts_with("albedo.") && n != "depth.Z").collect();
    let err = Frame::from_exr_bytes(&exr_single(W, H, &planes, Sample::F32), &Limits::default()).unwrap_err();
    match &err {
        FrameError::MissingChannels { missing, available, .. } => {
            assert_eq!(missing, &["albedo.R", "albedo.G", "albedo.B", "depth.Z"]);
            assert!(available.contains(&"diffuse.R".to_string()));
        }
        other => panic!("unexpected {other:?}"),
    }
    let msg = err.to_string();
    assert!(msg.contains("missing channels: albedo.R, albedo.G, albedo.B, depth.Z"), "{msg}");
}

#[test]
fn parts_of_different_sizes_are_refused() {
    let planes = named_planes(W, H, false);
    let parts = by_part(&planes);
    let mut spec: Vec<_> = parts.iter().map(|(p, l)| (p.as_str(), (W, H), l.clone())).collect();
    let last = spec.len() - 1;
    spec[last].1 = (W + 1, H);
    for (_, d) in spec[last].2.iter_mut() {
        d.resize((W + 1) * H, 0.0);
    }
    let err = Frame::from_exr_bytes(&exr_multi(&spec, Sample::F32), &Limits::default()).unwrap_err();
    assert!(matches!(err, FrameError::SizeMismatch { size: (20, 13), expected: (19, 13), .. }), "{err:?}");
    assert!(err.to_string().contains("is 20x13 but"), "{err}");
}

#[test]
fn frames_over_the_pixel_limit_are_refused_before_decoding() {
    let planes = named_planes(W, H, false);
    let bytes = exr_single(W, H, &planes, Sample::F32);
    let err = Frame::from_exr_bytes(&bytes, &Limits { max_pixels: 100 }).unwrap_err();
    assert_eq!(err, FrameError::TooLarge { width: W, height: H, pixels: (W * H) as u64, limit: 100 });
}

#[test]
fn empty_frames_are_refused() {
    let err = Frame::from_planes(0, 4, vec![], &[], &ChannelMaps::default()).unwrap_err();
    assert_eq!(err, FrameError::Empty { width: 0, height: 4 });
}

#[test]
fn truncated_files_are_refused() {
    let bytes = exr_single(W, H, &named_planes(W, H, false), Sample::F32);
    for cut in [10, bytes.len() / 3, bytes.len() - 7] {
        let err = Frame::from_exr_bytes(&bytes[..cut], &Limits::default()).unwrap_err();
        assert!(matches!(err, FrameError::Truncated(_) | FrameError::Corrupt(_)), "cut at {cut}: {err:?}");
    }
}

#[test]
fn a_file_read_a_block_at_a_time_decodes_and_fails_as_its_bytes_do() {
    // `mcdenoise run` and the workers read the frame's file through a buffered reader.
    let dir = tempfile::tempdir().unwrap();
    let planes = named_planes(W, H, true);
    let bytes = exr_single(W, H, &planes, Sample::F32);
    let read = |cut: usize| {
        let path = dir.path().join(format!("cut-{cut}.exr"));
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let file = std::io::BufReader::with_capacity(64, std::fs::File::open(&path).unwrap());
        let from_file =
            Frame::from_exr_reader_carrying(file, &Limits::default(), &Carry::default(), &ChannelMaps::default());
        let from_bytes = Frame::from_exr_bytes_carrying(
            &bytes[..cut],
            &Limits::default(),
            &Carry::default(),
            &ChannelMaps::default(),
        );
        // References (`--reference`, the daemon's reference uploads) are read the same way.
        let file = std::io::BufReader::with_capacity(64, std::fs::File::open(&path).unwrap());
        let reference = (
            Frame::reference_from_exr_reader(file, &Limits::default()),
            Frame::reference_from_exr_bytes(&bytes[..cut], &Limits::default()),
        );
        ((from_file.map(|(f, _)| f), from_bytes.map(|(f, _)| f)), reference)
    };
    let ((frame, _), (reference, reference_bytes)) = read(bytes.len());
    assert_same_as_planes(&frame.unwrap(), &planes, 0.0);
    let (reference, reference_bytes) = (reference.unwrap(), reference_bytes.unwrap());
    assert_eq!(reference.color(), reference_bytes.color());
    assert!(reference.color().iter().flatten().any(|&v| v != 0.0));
    for cut in [0, 10, bytes.len() / 3, bytes.len() - 7] {
        let ((from_file, from_bytes), (reference, reference_bytes)) = read(cut);
        for (a, b) in
            [(from_file.unwrap_err(), from_bytes.unwrap_err()), (reference.unwrap_err(), reference_bytes.unwrap_err())]
        {
            assert!(matches!(a, FrameError::Truncated(_) | FrameError::Corrupt(_)), "cut at {cut}: {a:?}");
            assert_eq!(a, b, "cut at {cut}");
        }
    }
}

#[test]
fn wrong_magic_and_garbage_are_refused() {
    let err = Frame::from_exr_bytes(b"P6\n4 4\n255\n................................", &Limits::default()).unwrap_err();
    assert!(matches!(err, FrameError::Corrupt(_)), "{err:?}");
    let err = Frame::from_exr_bytes(&[], &Limits::default()).unwrap_err();
    assert!(matches!(err, FrameError::Truncated(_) | FrameError::Corrupt(_)), "{err:?}");
}

#[test]
fn corrupt_pixel_data_is_refused() {
    let mut bytes = exr_single(W, H, &named_planes(W, H, false), Sample::F32);
    let n = bytes.len();
    for b in &mut bytes[n - 200..] {
        *b ^= 0x5a;
    }
    assert!(Frame::from_exr_bytes(&bytes, &Limits::default()).is_err());
}

#[test]
fn duplicate_channels_across_parts_are_refused() {
    let planes = named_planes(W, H, false);
    let parts = by_part(&planes);
    let mut spec: Vec<_> = parts.iter().map(|(p, l)| (p.as_str(), (W, H), l.clone())).collect();
    // Part `diffuse` holds both `R` and `diffuse.R`: both are diffuse.R.
    let diffuse = spec.iter_mut().find(|(p, _, _)| *p == "diffuse").unwrap();
    diffuse.2.push(("diffuse.R".to_string(), vec![0.0; W * H]));
    let err = Frame::from_exr_bytes(&exr_multi(&spec, Sample::F32), &Limits::default()).unwrap_err();
    assert_eq!(err, FrameError::DuplicateChannel("diffuse.R".into()));
}

#[test]
fn non_finite_samples_are_replaced_and_counted() {
    let mut planes = named_planes(W, H, true);
    let set = |planes: &mut Vec<(String, Vec<f32>)>, name: &str, i: usize, v: f32| {
        planes.iter_mut().find(|(n, _)| n == name).unwrap().1[i] = v;
    };
    set(&mut planes, "diffuse.G", 3, f32::NAN);
    set(&mut planes, "diffuse.B", 4, f32::INFINITY);
    set(&mut planes, "depth.Z", 5, f32::NEG_INFINITY);
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
    assert_eq!(frame.sanitized.total, 3);
    assert_eq!(frame.sanitized.by_buffer["diffuse"], 2);
    assert_eq!(frame.sanitized.by_buffer["depth"], 1);
    assert_eq!(frame.f32_plane(Buffer::Diffuse, 1)[3], 0.0);
    assert_eq!(frame.f32_plane(Buffer::Depth, 0)[5], 0.0);
}

#[test]
fn reference_needs_only_a_color() {
    let planes: Vec<_> = named_planes(W, H, false)
        .into_iter()
        .filter(|(n, _)| n.starts_with("diffuse.") || n.starts_with("specular."))
        .collect();
    let frame = Frame::reference_from_exr_bytes(&exr_single(W, H, &planes, Sample::F32), &Limits::default()).unwrap();
    assert_eq!(frame.color()[0][0], frame.f32_plane(Buffer::Diffuse, 0)[0] + frame.f32_plane(Buffer::Specular, 0)[0]);
    let only_albedo: Vec<_> = named_planes(W, H, false).into_iter().filter(|(n, _)| n.starts_with("albedo.")).collect();
    let err =
        Frame::reference_from_exr_bytes(&exr_single(W, H, &only_albedo, Sample::F32), &Limits::default()).unwrap_err();
    assert!(err.to_string().contains("R, G, B (or diffuse"), "{err}");
}

#[test]
fn a_renderers_infinitely_far_depth_is_no_hit_in_every_depth_channel() {
    // Backgrounds written as 1e10 (Blender Cycles) or 1e30, in the canonical channel and in
    // an alias; a depth just under the bound is a distance and stays.
    for name in ["depth.Z", "depth"] {
        let mut planes = named_planes(W, H, false);
        let depth = planes.iter_mut().find(|(n, _)| n == "depth.Z").unwrap();
        depth.0 = name.to_string();
        depth.1[0] = 1e10;
        depth.1[1] = 1e30;
        depth.1[2] = 0.99e9;
        let kept = depth.1.clone();
        let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
        let got = frame.f32_plane(Buffer::Depth, 0);
        assert_eq!(&got[..3], &[0.0, 0.0, 0.99e9], "{name}");
        assert_eq!(&got[3..], &kept[3..], "{name}: the other depths as they are");
        assert_eq!(frame.sanitized.total, 0, "a background distance is not bad input");
    }
}

#[test]
fn cycles_passes_give_the_diffuse_specular_split_and_missing_variances_are_zero() {
    let (bytes, planes) = cycles_frame(W, H, |_| true);
    let frame = frame_of(&bytes);
    let get = |n: &str| planes.iter().find(|(k, _)| k == n).unwrap().1.clone();
    for (i, c) in ["R", "G", "B"].into_iter().enumerate() {
        assert!(max_rel_diff(frame.f32_plane(Buffer::Diffuse, i), &get(&format!("diffuse.{c}"))) < 1e-5);
        let s = get(&format!("specular.{c}"));
        let err = frame.f32_plane(Buffer::Specular, i).iter().zip(&s).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(err < 1e-5, "specular.{c} off by {err}");
    }
    // Cycles' background distance is "no hit".
    assert_eq!(frame.f32_plane(Buffer::Depth, 0)[0], 0.0);
    assert_eq!(frame.f32_plane(Buffer::Depth, 0)[1], get("depth.Z")[1]);
    assert_eq!(
        frame.missing_variances,
        ["diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance"]
    );
    assert!(!frame.plane(Buffer::DiffuseVariance, 0).any_nonzero());
    // The header check the daemon runs at submission accepts it too.
    let names: Vec<String> = {
        let info = mcdenoise::frame::read_header(std::io::Cursor::new(&bytes), &Limits::default()).unwrap();
        info.channels
    };
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    mcdenoise::frame::check_required(&refs, mcdenoise::frame::layout::REQUIRED, &ChannelMaps::default()).unwrap();
}

#[test]
fn a_frame_without_any_variance_is_accepted_and_reports_it() {
    let planes: Vec<_> = named_planes(W, H, true).into_iter().filter(|(n, _)| !n.contains("Variance")).collect();
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
    assert_eq!(frame.missing_variances.len(), 6, "{:?}", frame.missing_variances);
    assert!(frame.has(Buffer::CovarianceVariance));
    // Without normals it is still refused, naming them.
    let planes: Vec<_> = planes.into_iter().filter(|(n, _)| !n.starts_with("normal")).collect();
    let err = Frame::from_exr_bytes(&exr_single(W, H, &planes, Sample::F32), &Limits::default()).unwrap_err();
    assert!(err.to_string().contains("normal.R"), "{err}");
}

#[test]
fn cycles_frames_lacking_passes_are_named_in_blender_terms() {
    // Without the Diffuse passes: accepted as a frame without the split, all light in the
    // diffuse slot (the `beauty` variant's input).
    let (bytes, _) = cycles_frame(W, H, |p| !p.starts_with("Diffuse"));
    let frame = frame_of(&bytes);
    assert!(frame.beauty_only);
    assert!(frame.f32_plane(Buffer::Specular, 0).iter().all(|v| *v == 0.0));
    assert!(!frame_of(&cycles_frame(W, H, |_| true).0).beauty_only);
    // Without Denoising Data: refused, saying which option to enable.
    let (bytes, _) = cycles_frame(W, H, |p| !p.starts_with("Denoising") && p != "Depth");
    let err = Frame::from_exr_bytes(&bytes, &Limits::default()).unwrap_err().to_string();
    assert!(
        err.contains("albedo.R") && err.contains("enable View Layer Properties > Passes > Data > Denoising Data"),
        "{err}"
    );
}

#[test]
fn a_beauty_albedo_normal_frame_is_read_with_the_beauty_as_its_diffuse() {
    let beauty: Vec<f32> = (0..W * H).map(|i| 0.25 + (i % 7) as f32).collect();
    let planes: Vec<_> = named_planes(W, H, false)
        .into_iter()
        .filter(|(n, _)| n.starts_with("albedo.") || n.starts_with("normal."))
        .chain(["R", "G", "B"].map(|c| (c.to_string(), beauty.clone())))
        .collect();
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
    assert!(frame.beauty_only);
    assert_eq!(frame.f32_plane(Buffer::Diffuse, 1), &beauty[..]);
    assert!(frame.f32_plane(Buffer::Specular, 2).iter().all(|v| *v == 0.0));
    assert!(frame.f32_plane(Buffer::Depth, 0).iter().all(|v| *v == 0.0), "no depth: 0, no hit");
    // A depth the file has is kept.
    let with_depth: Vec<_> = planes.iter().cloned().chain([("depth.Z".to_string(), vec![3.0; W * H])]).collect();
    let frame = frame_of(&exr_single(W, H, &with_depth, Sample::F32));
    assert!(frame.beauty_only && frame.f32_plane(Buffer::Depth, 0).iter().all(|v| *v == 3.0));
    // Without normals it is refused, naming them.
    let planes: Vec<_> = planes.into_iter().filter(|(n, _)| !n.starts_with("normal")).collect();
    let err = Frame::from_exr_bytes(&exr_single(W, H, &planes, Sample::F32), &Limits::default()).unwrap_err();
    assert!(err.to_string().contains("normal.R"), "{err}");
    assert!(err.to_string().contains("needs an albedo and a normal (then the `beauty` variant takes it"), "{err}");
}

/// The kind read from a header's channel names alone (what `mcdenoise run` loads its
/// networks from while the frame decodes) is the decoded frame's.
#[test]
fn a_headers_channels_tell_the_frames_kind() {
    let fixtures = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/frames");
    let beauty: Vec<_> = named_planes(W, H, false)
        .into_iter()
        .filter(|(n, _)| n.starts_with("albedo.") || n.starts_with("normal."))
        .chain(["R", "G", "B"].map(|c| (c.to_string(), vec![0.5; W * H])))
        .collect();
    let mut files = vec![
        (exr_single(W, H, &named_planes(W, H, true), Sample::F32), (false, true)),
        (exr_single(W, H, &named_planes(W, H, false), Sample::F32), (false, false)),
        (exr_single(W, H, &beauty, Sample::F32), (true, false)),
        (cycles_frame(W, H, |_| true).0, (false, false)),
        (cycles_frame(W, H, |p| !p.starts_with("Diffuse")).0, (true, false)),
    ];
    for (name, expected) in [("cornell-spp8.exr", (false, true)), ("cornell-nocov-spp8.exr", (false, false))] {
        files.push((std::fs::read(fixtures.join(name)).unwrap(), expected));
    }
    let maps = ChannelMaps::default();
    for (i, (bytes, (beauty_only, covariance))) in files.iter().enumerate() {
        let info = read_header(std::io::Cursor::new(bytes), &Limits::default()).unwrap();
        let names: Vec<&str> = info.channels.iter().map(String::as_str).collect();
        let kind = FrameKind::of_channels(&names, &maps);
        assert_eq!(kind, FrameKind { beauty_only: *beauty_only, covariance: *covariance }, "file {i}: {names:?}");
        assert_eq!(kind, frame_of(bytes).kind(), "file {i}");
    }
}

#[test]
fn a_split_frame_as_the_beauty_variant_takes_it() {
    let planes = named_planes(W, H, true);
    let frame = frame_of(&exr_single(W, H, &planes, Sample::F32));
    assert!(!frame.beauty_only);
    let b = frame.to_beauty();
    assert!(b.beauty_only);
    let sum = frame.diffuse_plus_specular();
    for c in 0..3 {
        assert_eq!(b.f32_plane(Buffer::Diffuse, c), &sum[c][..]);
        assert!(b.f32_plane(Buffer::Specular, c).iter().all(|v| *v == 0.0));
        assert_eq!(b.plane(Buffer::Albedo, c).to_vec(), frame.plane(Buffer::Albedo, c).to_vec());
    }
    assert!(!b.has(Buffer::Covariance) && !b.has(Buffer::CovarianceVariance));
    for var in [Buffer::DiffuseVariance, Buffer::SpecularVariance, Buffer::NormalVariance, Buffer::DepthVariance] {
        assert!(!b.planes(var).iter().any(PlaneRef::any_nonzero), "{var:?}");
    }
    assert!(frame.plane(Buffer::DiffuseVariance, 0).any_nonzero(), "the original keeps its variances");
    assert_eq!(b.f32_plane(Buffer::Depth, 0), frame.f32_plane(Buffer::Depth, 0));
}

// --- What a result keeps of its input ------------------------------------------------------

use exr::prelude::{f16, AnyChannel, FlatSamples, IntegerBounds, LayerAttributes, Text, Vec2, WritableImage};
use mcdenoise::frame::{Carry, ALPHA};

fn carry(all: bool) -> Carry {
    Carry { all, written: ["R", "G", "B"].map(String::from).to_vec() }
}

/// Decodes `bytes` carrying `carry`, and encodes the result with zeros for `R,G,B`.
fn round_trip(bytes: &[u8], carry: &Carry) -> (Vec<u8>, Vec<String>) {
    let (frame, carried) =
        Frame::from_exr_bytes_carrying(bytes, &Limits::default(), carry, &ChannelMaps::default()).unwrap();
    let names = carried.names();
    let n = frame.pixels();
    let denoised = ["R", "G", "B"].map(|c| (c.to_string(), vec![0.0; n])).to_vec();
    (carried.encode(frame, denoised).unwrap(), names)
}

#[test]
fn a_result_keeps_the_inputs_windows_attributes_and_channels_bit_for_bit() {
    let (w, h) = (97, 61);
    let placement = Placement {
        origin: (-3, 5),
        display: IntegerBounds::new((0, 0), (90, 64)),
        pixel_aspect: 1.25,
        attributes: renderer_attributes(),
    };
    let planes = named_planes(w, h, true);
    let mut channels: Vec<AnyChannel<FlatSamples>> = Vec::new();
    for (name, data) in &planes {
        let mut data = data.clone();
        if name == "albedo.G" {
            data[7] = f32::NAN; // a network input with a NaN: replaced in the frame, kept here
        }
        let samples = match name.as_str() {
            // a network input in half precision
            "depth.Z" => FlatSamples::F16(data.iter().map(|v| f16::from_f32(*v)).collect()),
            _ => FlatSamples::F32(data),
        };
        channels.push(AnyChannel::new(name.as_str(), samples));
    }
    let n = w * h;
    channels
        .push(AnyChannel::new("A", FlatSamples::F16((0..n).map(|i| f16::from_f32((i % 7) as f32 / 6.0)).collect())));
    channels.push(AnyChannel::new("crypto00.R", FlatSamples::F16((0..n).map(|i| f16::from_bits(i as u16)).collect())));
    channels.push(AnyChannel::new("objectId", FlatSamples::U32((0..n as u32).map(|i| i * 16_777_259).collect())));
    let mut emission: Vec<f32> = (0..n).map(|i| i as f32 * 0.25).collect();
    emission[3] = f32::INFINITY;
    emission[4] = f32::from_bits(0x7fc0_1234);
    channels.push(AnyChannel::new("emission.R", FlatSamples::F32(emission)));
    let input = exr_placed(w, h, &placement, channels);

    let (out, carried) = round_trip(&input, &carry(true));
    assert!(carried.contains(&ALPHA.to_string()) && carried.contains(&"objectId".to_string()), "{carried:?}");
    let (input, out) = (read_exr(&input), read_exr(&out));
    assert_eq!(out.layer_data.len(), 1, "a single-part result");
    assert_eq!(out.attributes.display_window, placement.display);
    assert_eq!(out.attributes.pixel_aspect, 1.25);
    let layer = &out.layer_data[0];
    assert_eq!(layer.attributes.layer_position, Vec2(-3, 5));
    assert_eq!(layer.size, Vec2(w, h));
    let want = renderer_attributes();
    assert_eq!(layer.attributes.world_to_camera, want.world_to_camera);
    assert_eq!(layer.attributes.software_name, want.software_name);
    for (name, value) in &want.other {
        assert_eq!(layer.attributes.other.get(name), Some(value), "{name}");
    }
    // Every input channel comes back bit for bit in its own type, beside R,G,B.
    let by_name = |image: &exr::prelude::Image<exr::prelude::Layers<exr::prelude::AnyChannels<FlatSamples>>>| {
        image.layer_data[0]
            .channel_data
            .list
            .iter()
            .map(|c| (c.name.to_string(), bits(&c.sample_data)))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    let (got, mut want) = (by_name(&out), by_name(&input));
    for c in ["R", "G", "B"] {
        want.insert(c.to_string(), ("f32", vec![0; n]));
    }
    assert_eq!(got.keys().collect::<Vec<_>>(), want.keys().collect::<Vec<_>>());
    for (name, samples) in &want {
        assert!(got[name] == *samples, "{name} changed");
    }
}

#[test]
fn without_all_only_the_alpha_is_carried_and_the_frame_reads_the_same() {
    let (w, h) = (W, H);
    let planes = named_planes(w, h, true);
    let mut channels = f32_channels(&planes);
    channels.push(AnyChannel::new("A", FlatSamples::F32(vec![0.5; w * h])));
    channels.push(AnyChannel::new("crypto00.R", FlatSamples::F32(vec![1.0; w * h])));
    let bytes = exr_placed(w, h, &Placement::plain(w, h), channels);
    let (frame, carried) =
        Frame::from_exr_bytes_carrying(&bytes, &Limits::default(), &carry(false), &ChannelMaps::default()).unwrap();
    assert_eq!(carried.names(), [ALPHA]);
    assert_eq!(carried.header.origin(), (0, 0));
    assert_same_as_planes(&frame, &planes, 0.0);
    // Denoised layers replace the input's channels of their names under `all`.
    let with_diffuse =
        Carry { all: true, written: ["R", "G", "B", "diffuse.R", "diffuse.G", "diffuse.B"].map(String::from).to_vec() };
    let (_, carried) =
        Frame::from_exr_bytes_carrying(&bytes, &Limits::default(), &with_diffuse, &ChannelMaps::default()).unwrap();
    let names = carried.names();
    assert!(!names.iter().any(|n| n.starts_with("diffuse.")) && names.contains(&"specular.R".to_string()));
}

#[test]
fn cycles_results_keep_the_combined_parts_attributes_and_alpha_and_every_pass() {
    let (bytes, _) = cycles_frame(W, H, |_| true);
    // The same file with attributes on the Combined part and an origin on every part.
    let mut image = read_exr(&bytes);
    for layer in image.layer_data.iter_mut() {
        layer.attributes.layer_position = Vec2(-8, -8);
        if layer.attributes.layer_name.as_ref().is_some_and(|n| n == "ViewLayer.Combined") {
            let mut a = renderer_attributes();
            a.layer_name = layer.attributes.layer_name.clone();
            layer.attributes = LayerAttributes { layer_position: Vec2(-8, -8), ..a };
        }
    }
    image.attributes.display_window = IntegerBounds::new((0, 0), (W - 8, H - 8));
    let mut input = std::io::Cursor::new(Vec::new());
    image.write().to_buffered(&mut input).unwrap();
    let input = input.into_inner();

    let (out, carried) = round_trip(&input, &carry(true));
    assert!(carried.contains(&ALPHA.to_string()));
    assert!(!carried.iter().any(|n| n.starts_with("ViewLayer.Combined.")), "the beauty is replaced: {carried:?}");
    let out = read_exr(&out);
    let layer = &out.layer_data[0];
    assert_eq!(layer.attributes.layer_name, None);
    assert_eq!(layer.attributes.layer_position, Vec2(-8, -8));
    assert_eq!(out.attributes.display_window, IntegerBounds::new((0, 0), (W - 8, H - 8)));
    assert_eq!(
        layer.attributes.other.get(&Text::from("renderer/scene")),
        renderer_attributes().other.get(&Text::from("renderer/scene"))
    );
    let got: std::collections::BTreeMap<String, _> =
        layer.channel_data.list.iter().map(|c| (c.name.to_string(), bits(&c.sample_data))).collect();
    for part in &image.layer_data {
        let prefix = part.attributes.layer_name.as_ref().unwrap().to_string();
        for c in &part.channel_data.list {
            let name = format!("{prefix}.{}", c.name);
            match name.as_str() {
                "ViewLayer.Combined.A" => assert!(got["A"] == bits(&c.sample_data)),
                n if n.starts_with("ViewLayer.Combined.") => assert!(!got.contains_key(n)),
                n => assert!(got.get(n) == Some(&bits(&c.sample_data)), "{n}"),
            }
        }
    }
}

#[test]
fn parts_that_start_at_different_points_are_refused() {
    let planes = named_planes(W, H, false);
    let parts = by_part(&planes);
    let spec: Vec<_> = parts.iter().map(|(p, l)| (p.as_str(), (W, H), l.clone())).collect();
    let mut image = read_exr(&exr_multi(&spec, Sample::F32));
    image.layer_data[1].attributes.layer_position = Vec2(0, -2);
    let mut bytes = std::io::Cursor::new(Vec::new());
    image.write().to_buffered(&mut bytes).unwrap();
    let err = Frame::from_exr_bytes(&bytes.into_inner(), &Limits::default()).unwrap_err();
    assert!(matches!(err, FrameError::PartOrigins { origin: (0, -2), expected: (0, 0), .. }), "{err}");
}

#[test]
fn a_clone_shares_its_planes_until_one_buffer_is_changed() {
    let frame = mcdenoise::engine::synthetic_frame(16, 8, true);
    let mut copy = frame.clone();
    copy.planes_mut(Buffer::Diffuse)[0][5] = 42.0;
    // The changed buffer is the clone's own; the others are still the original's memory.
    assert_eq!(copy.f32_plane(Buffer::Diffuse, 0)[5], 42.0);
    assert_ne!(frame.f32_plane(Buffer::Diffuse, 0)[5], 42.0);
    assert_ne!(copy.f32_plane(Buffer::Diffuse, 0).as_ptr(), frame.f32_plane(Buffer::Diffuse, 0).as_ptr());
    for b in [Buffer::Albedo, Buffer::Normal, Buffer::Covariance, Buffer::SpecularVariance] {
        assert_eq!(copy.plane(b, 0).as_ptr(), frame.plane(b, 0).as_ptr(), "{}", b.name());
    }
    // Taking a shared buffer out copies it; the original keeps its planes.
    let taken = copy.take(Buffer::Albedo).unwrap();
    assert_eq!(taken[0], frame.plane(Buffer::Albedo, 0).to_vec());
    assert!(!copy.has(Buffer::Albedo) && frame.has(Buffer::Albedo));
}
