//! Display previews of linear HDR frames for the dashboard: an optional crop, a box
//! downscale in linear light, an exposure in stops, a view transform, 8-bit sRGB, PNG.
//!
//! Pure and synchronous: the core reads the sources and caches the answers
//! (`jobs::previews`); `GET /v1/jobs/{id}/preview` is its transport.
//!
//! View transforms:
//! - `standard`: the sRGB transfer function (IEC 61966-2-1) on the exposed value clamped to
//!   [0, 1], as a display shows a linear frame with no tone mapping (highlights clip);
//! - `filmic`: Narkowicz's fit of the ACES reference rendering transform
//!   (`x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14)`), then the sRGB transfer function, which
//!   rolls highlights off instead of clipping them.

use std::path::Path;

/// A linear RGB image, planar, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Rgb {
    pub width: usize,
    pub height: usize,
    pub planes: [Vec<f32>; 3],
}

impl Rgb {
    pub fn new(width: usize, height: usize, planes: [Vec<f32>; 3]) -> Rgb {
        debug_assert!(planes.iter().all(|p| p.len() == width * height));
        Rgb { width, height, planes }
    }
}

/// How linear values become display values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum View {
    #[default]
    Standard,
    Filmic,
}

impl View {
    pub const ALL: [View; 2] = [View::Standard, View::Filmic];

    pub fn name(self) -> &'static str {
        match self {
            View::Standard => "standard",
            View::Filmic => "filmic",
        }
    }
}

impl std::str::FromStr for View {
    type Err = String;

    fn from_str(s: &str) -> Result<View, String> {
        View::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| format!("unknown view `{}` (expected standard or filmic)", crate::error::truncate(s, 32)))
    }
}

/// A rectangle of the frame in pixels, origin at the top left of its data window.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Region {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

impl std::str::FromStr for Region {
    type Err = String;

    /// `x,y,width,height`: decimal digits only (at most 5 each), the sizes from 1 and
    /// without a leading zero, as the OpenAPI document's pattern says.
    fn from_str(s: &str) -> Result<Region, String> {
        let bad = || format!("bad region `{}`: expected x,y,width,height in pixels", crate::error::truncate(s, 64));
        let parts: Vec<&str> = s.split(',').collect();
        let plain = |v: &&str| (1..=5).contains(&v.len()) && v.bytes().all(|b| b.is_ascii_digit());
        if parts.len() != 4 || !parts.iter().all(plain) || parts[2..].iter().any(|v| v.starts_with('0')) {
            return Err(bad());
        }
        let n: Vec<usize> = parts.iter().map(|v| v.parse().map_err(|_| bad())).collect::<Result<_, _>>()?;
        Ok(Region { x: n[0], y: n[1], width: n[2], height: n[3] })
    }
}

/// Exposures accepted, in stops.
pub const EXPOSURE_RANGE: std::ops::RangeInclusive<f32> = -20.0..=20.0;
/// Longest side of a preview accepted, in pixels.
pub const MAX_SIZE_RANGE: std::ops::RangeInclusive<usize> = 16..=8192;
/// Longest side of a preview when the request names none.
pub const DEFAULT_MAX_SIZE: usize = 1024;

/// What to render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spec {
    /// Stops: values are multiplied by 2^exposure before the view transform.
    pub exposure: f32,
    pub view: View,
    /// The preview's longer side is at most this many pixels (the frame, or the region, is
    /// shrunk by the smallest whole factor that fits).
    pub max_size: usize,
    pub region: Option<Region>,
}

impl Default for Spec {
    fn default() -> Spec {
        Spec { exposure: 0.0, view: View::Standard, max_size: DEFAULT_MAX_SIZE, region: None }
    }
}

impl Spec {
    /// Checks the ranges; the message names the value that is wrong.
    pub fn check(&self) -> Result<(), String> {
        if !self.exposure.is_finite() || !EXPOSURE_RANGE.contains(&self.exposure) {
            return Err(format!(
                "exposure must be {} to {} stops, not {}",
                EXPOSURE_RANGE.start(),
                EXPOSURE_RANGE.end(),
                self.exposure
            ));
        }
        if !MAX_SIZE_RANGE.contains(&self.max_size) {
            return Err(format!(
                "max_size must be {} to {} pixels, not {}",
                MAX_SIZE_RANGE.start(),
                MAX_SIZE_RANGE.end(),
                self.max_size
            ));
        }
        Ok(())
    }

    /// A stable text form: the cache key of a rendering.
    pub fn key(&self) -> String {
        let region = self.region.map_or(String::new(), |r| format!("{},{},{},{}", r.x, r.y, r.width, r.height));
        format!("{}:{}:{}:{}", self.exposure.to_bits(), self.view.name(), self.max_size, region)
    }
}

/// The sRGB transfer function (linear [0, 1] to encoded [0, 1]).
fn srgb_oetf(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Narkowicz's ACES fit.
fn aces_fit(x: f32) -> f32 {
    (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
}

/// One linear value (already exposed) as an 8-bit display value.
pub fn display(v: f32, view: View) -> u8 {
    let v = if v.is_finite() { v.max(0.0) } else { 0.0 };
    let v = match view {
        View::Standard => v.min(1.0),
        View::Filmic => aces_fit(v).clamp(0.0, 1.0),
    };
    (srgb_oetf(v) * 255.0 + 0.5) as u8
}

/// Renders `spec` of `src`: 8-bit RGB, interleaved, with its size.
/// `spec`'s ranges are the API's to check ([`Spec::check`]); only a region outside the
/// frame is refused here.
pub fn render(src: &Rgb, spec: &Spec) -> Result<(usize, usize, Vec<u8>), String> {
    let region = spec.region.unwrap_or(Region { x: 0, y: 0, width: src.width, height: src.height });
    if region.x.saturating_add(region.width) > src.width || region.y.saturating_add(region.height) > src.height {
        return Err(format!(
            "the region {},{},{},{} is not inside the {}x{} frame",
            region.x, region.y, region.width, region.height, src.width, src.height
        ));
    }
    let factor = region.width.max(region.height).div_ceil(spec.max_size.max(1)).max(1);
    let (w, h) = (region.width.div_ceil(factor), region.height.div_ceil(factor));
    let gain = spec.exposure.exp2();
    let mut out = vec![0u8; w * h * 3];
    for oy in 0..h {
        let y0 = region.y + oy * factor;
        let y1 = (y0 + factor).min(region.y + region.height);
        for ox in 0..w {
            let x0 = region.x + ox * factor;
            let x1 = (x0 + factor).min(region.x + region.width);
            let n = ((y1 - y0) * (x1 - x0)) as f32;
            for (c, plane) in src.planes.iter().enumerate() {
                let mut sum = 0.0f32;
                for y in y0..y1 {
                    let row = &plane[y * src.width + x0..y * src.width + x1];
                    sum += row.iter().map(|v| if v.is_finite() { *v } else { 0.0 }).sum::<f32>();
                }
                out[(oy * w + ox) * 3 + c] = display(sum / n * gain, spec.view);
            }
        }
    }
    Ok((w, h, out))
}

/// 8-bit RGB as PNG (sRGB chunk set).
pub fn encode_png(width: usize, height: usize, rgb: &[u8]) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width as u32, height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    encoder.set_compression(png::Compression::Fast);
    encoder.write_header()?.write_image_data(rgb)?;
    Ok(out)
}

/// Reads `R,G,B` of the first part that has them (any sample type) from an EXR file.
pub fn read_rgb_exr(path: &Path) -> Result<Rgb, exr::error::Error> {
    use exr::prelude::*;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgb_channels(
            |size: Vec2<usize>, _: &RgbChannels| {
                let n = size.width() * size.height();
                Rgb::new(size.width(), size.height(), [vec![0.0; n], vec![0.0; n], vec![0.0; n]])
            },
            |rgb: &mut Rgb, pos: Vec2<usize>, (r, g, b): (f32, f32, f32)| {
                let i = pos.y() * rgb.width + pos.x();
                rgb.planes[0][i] = r;
                rgb.planes[1][i] = g;
                rgb.planes[2][i] = b;
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_file(path)?;
    Ok(image.layer_data.channel_data.pixels)
}

/// Writes `R,G,B` as a half-float EXR (ZIP): what a preview is made from once a job's
/// uploaded frames are gone.
pub fn write_rgb_exr(path: &Path, rgb: &Rgb) -> std::io::Result<()> {
    let named = ["R", "G", "B"].into_iter().zip(rgb.planes.iter().map(Vec::as_slice));
    let bytes = crate::frame::write_planes(
        rgb.width,
        rgb.height,
        named,
        crate::frame::SampleType::F16,
        exr::prelude::Encoding::SMALL_LOSSLESS,
    )
    .map_err(std::io::Error::other)?;
    crate::atomic::write(path, &bytes)
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;

    fn ramp(w: usize, h: usize) -> Rgb {
        let p: Vec<f32> = (0..w * h).map(|i| i as f32 / (w * h) as f32).collect();
        Rgb::new(w, h, [p.clone(), p.iter().map(|v| v * 0.5).collect(), vec![1.0; w * h]])
    }

    #[test]
    fn the_transfer_functions_map_black_white_and_middle_grey() {
        assert_eq!(display(0.0, View::Standard), 0);
        assert_eq!(display(1.0, View::Standard), 255);
        assert_eq!(display(8.0, View::Standard), 255);
        // 18 % grey is 118 in sRGB.
        assert_eq!(display(0.18, View::Standard), 118);
        assert_eq!(display(f32::NAN, View::Standard), 0);
        assert_eq!(display(-1.0, View::Filmic), 0);
        // The filmic view rolls highlights off: 1.0 is below white, 16 nearly white.
        assert!(display(1.0, View::Filmic) < 240, "{}", display(1.0, View::Filmic));
        assert!(display(16.0, View::Filmic) >= 253);
        // and is monotonic.
        let values: Vec<u8> = (0..200).map(|i| display(i as f32 / 20.0, View::Filmic)).collect();
        assert!(values.windows(2).all(|w| w[0] <= w[1]));
    }

    #[test]
    fn exposure_scales_by_powers_of_two() {
        let src = Rgb::new(1, 1, [vec![0.25], vec![0.5], vec![0.125]]);
        let spec = Spec { exposure: 1.0, ..Spec::default() };
        let (_, _, px) = render(&src, &spec).unwrap();
        assert_eq!(px, vec![display(0.5, View::Standard), 255, display(0.25, View::Standard)]);
    }

    #[test]
    fn large_frames_shrink_by_a_whole_factor_averaging_linear_light() {
        let src = Rgb::new(4, 2, [vec![0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0], vec![0.0; 8], vec![0.0; 8]]);
        let (w, h, px) = render(&src, &Spec { max_size: 2, ..Spec::default() }).unwrap();
        assert_eq!((w, h), (2, 1));
        // Each 2x2 block averages to 0.5 before the transfer function.
        assert_eq!(px[0], display(0.5, View::Standard));
        assert_eq!(px[3], display(0.5, View::Standard));
        // A side that does not divide: the last block is partial.
        let (w, h, _) = render(&ramp(1000, 10), &Spec { max_size: 300, ..Spec::default() }).unwrap();
        assert_eq!((w, h), (250, 3));
    }

    #[test]
    fn a_region_is_cut_at_full_resolution() {
        let src = ramp(64, 32);
        let region = Region { x: 10, y: 5, width: 8, height: 4 };
        let (w, h, px) = render(&src, &Spec { region: Some(region), ..Spec::default() }).unwrap();
        assert_eq!((w, h), (8, 4));
        let i = 5 * 64 + 10;
        assert_eq!(px[0], display(src.planes[0][i], View::Standard));
        let outside = Region { x: 60, y: 0, width: 8, height: 4 };
        let e = render(&src, &Spec { region: Some(outside), ..Spec::default() }).unwrap_err();
        assert!(e.contains("not inside the 64x32 frame"), "{e}");
    }

    #[test]
    fn parameters_out_of_range_are_refused_naming_them() {
        let e = Spec { exposure: 40.0, ..Spec::default() }.check().unwrap_err();
        assert!(e.starts_with("exposure must be"), "{e}");
        assert!(Spec { exposure: f32::NAN, ..Spec::default() }.check().is_err());
        let e = Spec { max_size: 4, ..Spec::default() }.check().unwrap_err();
        assert!(e.starts_with("max_size must be"), "{e}");
        assert!("1,2,3".parse::<Region>().is_err());
        assert!("1,2,0,4".parse::<Region>().is_err());
        assert!("+1,2,3,4".parse::<Region>().is_err());
        assert!("1, 2,3,4".parse::<Region>().is_err());
        assert!("1,2,03,4".parse::<Region>().is_err());
        assert!("1,2,3,4,5".parse::<Region>().is_err());
        assert_eq!("1,2,3,4".parse::<Region>().unwrap(), Region { x: 1, y: 2, width: 3, height: 4 });
        assert!("aces".parse::<View>().unwrap_err().contains("standard or filmic"));
    }

    #[test]
    fn png_and_exr_round_trip() {
        let src = ramp(20, 10);
        let (w, h, pixels) = render(&src, &Spec::default()).unwrap();
        let png_bytes = encode_png(w, h, &pixels).unwrap();
        let decoder = png::Decoder::new(Cursor::new(&png_bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height, info.color_type), (20, 10, png::ColorType::Rgb));
        assert_eq!(&buf[..info.buffer_size()], &render(&src, &Spec::default()).unwrap().2[..]);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rgb.exr");
        write_rgb_exr(&path, &src).unwrap();
        let back = read_rgb_exr(&path).unwrap();
        assert_eq!((back.width, back.height), (20, 10));
        for c in 0..3 {
            for (a, b) in src.planes[c].iter().zip(&back.planes[c]) {
                assert!((a - b).abs() <= a.abs() * 1e-3 + 1e-4, "{a} vs {b} (half floats)");
            }
        }
    }
}
