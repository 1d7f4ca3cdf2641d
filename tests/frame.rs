//! Reading frames: EXR round trips in every supported form, aliases, and one specific error
//! per kind of bad input.

mod common;

use common::*;
use mcdenoise::frame::{write_exr, Buffer, Frame, FrameError, Limits, NamedPlanes, OutputLayer};

const W: usize = 19;
const H: usize = 13;

fn assert_same_as_planes(frame: &Frame, planes: &[(String, Vec<f32>)], tolerance: f32) {
    let expect = |name: &str| planes.iter().find(|(n, _)| n == name).map(|(_, d)| d.clone()).unwrap();
    for (buffer, names) in [
        (Buffer::Diffuse, ["diffuse.R", "diffuse.G", "diffuse.B"]),
        (Buffer::Normal, ["normal.R", "normal.G", "normal.B"]),
    ] {
        for (c, name) in names.iter().enumerate() {
            assert!(max_rel_diff(frame.plane(buffer, c), &expect(name)) <= tolerance, "{name}");
        }
    }
    assert!(max_rel_diff(frame.plane(Buffer::Depth, 0), &expect("depth.Z")) <= tolerance);
    assert!(max_rel_diff(frame.plane(Buffer::Covariance, 0), &expect("covariance")) <= tolerance);
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
    let frame = Frame::reference_from_exr_bytes(&bytes, &Limits::default()).unwrap();
    assert_eq!(frame.plane(Buffer::Color, 0), &r[..]);
    assert_eq!(frame.plane(Buffer::Color, 2), &b[..]);
    assert_eq!(frame.plane(Buffer::Diffuse, 1), &b[..]);
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
    let err = Frame::from_planes(0, 4, vec![], &[]).unwrap_err();
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
    assert_eq!(frame.plane(Buffer::Diffuse, 1)[3], 0.0);
    assert_eq!(frame.plane(Buffer::Depth, 0)[5], 0.0);
}

#[test]
fn reference_needs_only_a_color() {
    let planes: Vec<_> = named_planes(W, H, false)
        .into_iter()
        .filter(|(n, _)| n.starts_with("diffuse.") || n.starts_with("specular."))
        .collect();
    let frame = Frame::reference_from_exr_bytes(&exr_single(W, H, &planes, Sample::F32), &Limits::default()).unwrap();
    assert_eq!(frame.color()[0][0], frame.plane(Buffer::Diffuse, 0)[0] + frame.plane(Buffer::Specular, 0)[0]);
    let only_albedo: Vec<_> = named_planes(W, H, false).into_iter().filter(|(n, _)| n.starts_with("albedo.")).collect();
    let err =
        Frame::reference_from_exr_bytes(&exr_single(W, H, &only_albedo, Sample::F32), &Limits::default()).unwrap_err();
    assert!(err.to_string().contains("R, G, B (or diffuse"), "{err}");
}

#[test]
fn cycles_passes_give_the_diffuse_specular_split_and_missing_variances_are_zero() {
    let (bytes, planes) = cycles_frame(W, H, |_| true);
    let frame = frame_of(&bytes);
    let get = |n: &str| planes.iter().find(|(k, _)| k == n).unwrap().1.clone();
    for (i, c) in ["R", "G", "B"].into_iter().enumerate() {
        assert!(max_rel_diff(frame.plane(Buffer::Diffuse, i), &get(&format!("diffuse.{c}"))) < 1e-5);
        let s = get(&format!("specular.{c}"));
        let err = frame.plane(Buffer::Specular, i).iter().zip(&s).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(err < 1e-5, "specular.{c} off by {err}");
    }
    // Cycles' background distance is "no hit".
    assert_eq!(frame.plane(Buffer::Depth, 0)[0], 0.0);
    assert_eq!(frame.plane(Buffer::Depth, 0)[1], get("depth.Z")[1]);
    assert_eq!(
        frame.missing_variances,
        ["diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance"]
    );
    assert!(frame.plane(Buffer::DiffuseVariance, 0).iter().all(|v| *v == 0.0));
    // The header check the daemon runs at submission accepts it too.
    let names: Vec<String> = {
        let info = mcdenoise::frame::read_header(std::io::Cursor::new(&bytes), &Limits::default()).unwrap();
        info.channels
    };
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    mcdenoise::frame::check_required(&refs, mcdenoise::frame::layout::REQUIRED).unwrap();
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
    // Without the Diffuse passes: accepted, all light taken as diffuse, and said so.
    let (bytes, _) = cycles_frame(W, H, |p| !p.starts_with("Diffuse"));
    let frame = frame_of(&bytes);
    assert_eq!(frame.warnings, [mcdenoise::frame::renderers::CYCLES_NO_DIFFUSE]);
    assert!(frame.plane(Buffer::Specular, 0).iter().all(|v| *v == 0.0));
    assert!(frame_of(&cycles_frame(W, H, |_| true).0).warnings.is_empty());
    // Without Denoising Data: refused, saying which option to enable.
    let (bytes, _) = cycles_frame(W, H, |p| !p.starts_with("Denoising") && p != "Depth");
    let err = Frame::from_exr_bytes(&bytes, &Limits::default()).unwrap_err().to_string();
    assert!(err.contains("albedo.R") && err.contains("enable View Layer Properties > Passes > Data > Denoising Data"), "{err}");
}

#[test]
fn a_beauty_albedo_normal_frame_is_refused_naming_the_beauty_variant() {
    let planes: Vec<_> = named_planes(W, H, false)
        .into_iter()
        .filter(|(n, _)| n.starts_with("albedo.") || n.starts_with("normal."))
        .chain(["R", "G", "B"].map(|c| (c.to_string(), vec![0.5; W * H])))
        .collect();
    let err = Frame::from_exr_bytes(&exr_single(W, H, &planes, Sample::F32), &Limits::default()).unwrap_err();
    let err = err.to_string();
    assert!(err.contains("only beauty (R,G,B), albedo and normal") && err.contains("`beauty` variant"), "{err}");
}
