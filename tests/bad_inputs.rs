//! The bad-input corpus (`tests/bad-inputs/`): every case of `cases.json` sent to one daemon,
//! each answered with its own specific error (or accepted and failed, or accepted and
//! sanitized, as the case says), and a good frame served right after each.
//!
//! `cargo test --release --test integration -- --ignored bad_inputs::regenerate_corpus` rewrites the
//! files from the generator below; `BAD_INPUTS_ONLY=text` runs only the cases whose name
//! contains `text`. The manifest's format: `tests/bad-inputs/README.md` and [`Case`].

use crate::common;
use crate::daemon_common;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use bytes::Bytes;
use exr::prelude::{
    f16, AnyChannel, AnyChannels, Blocks, Compression, Encoding, FlatSamples, Image, ImageAttributes, IntegerBounds,
    Layer, LayerAttributes, LineOrder, SmallVec, Vec2, WritableImage,
};
use http_body_util::{BodyExt, StreamBody};
use hyper::body::Frame as BodyFrame;
use hyper::{Method, StatusCode};
use serde::Deserialize;
use serde_json::Value;

use common::{exr_single, named_planes, Sample};
use daemon_common::{frame, frame_without, reference, start, write, Daemon};
use mcdenoise::client::{body_bytes, grpc_connect, read_json, upload_stream, HttpClient};
use mcdenoise::grpc::pb;

fn corpus_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/bad-inputs")
}

// --- The generator -------------------------------------------------------------------------

/// Side of the small frames of the corpus.
const S: usize = 8;

/// Hand-written OpenEXR structures, for what the exr crate will not write: deep parts,
/// absurd sizes, broken attributes. An attribute is `name\0 type\0 size(i32 LE) value`; a
/// header is its attributes and a 0 byte.
mod raw {
    pub const MAGIC: [u8; 4] = [0x76, 0x2f, 0x31, 0x01];
    pub const TILED: u32 = 1 << 9;
    pub const DEEP: u32 = 1 << 11;
    pub const MULTIPART: u32 = 1 << 12;
    pub const FLOAT: i32 = 2;

    /// The channels every frame needs (`layout::REQUIRED`), sorted as EXR wants.
    pub const REQUIRED: [&str; 13] = [
        "albedo.B",
        "albedo.G",
        "albedo.R",
        "depth.Z",
        "diffuse.B",
        "diffuse.G",
        "diffuse.R",
        "normal.B",
        "normal.G",
        "normal.R",
        "specular.B",
        "specular.G",
        "specular.R",
    ];

    pub fn attribute(name: &str, kind: &str, value: &[u8]) -> Vec<u8> {
        attribute_sized(name, kind, value.len() as i32, value)
    }

    /// An attribute whose size field says `size`, whatever follows.
    pub fn attribute_sized(name: &str, kind: &str, size: i32, value: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        for s in [name, kind] {
            out.extend_from_slice(s.as_bytes());
            out.push(0);
        }
        out.extend_from_slice(&size.to_le_bytes());
        out.extend_from_slice(value);
        out
    }

    pub fn i32s(values: &[i32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    /// A `chlist` value: `(name, pixel type, sampling)`.
    pub fn channel_list(channels: &[(&str, i32, i32)]) -> Vec<u8> {
        let mut out = Vec::new();
        for (name, pixel_type, sampling) in channels {
            out.extend_from_slice(name.as_bytes());
            out.push(0);
            out.extend_from_slice(&pixel_type.to_le_bytes());
            out.extend_from_slice(&[0, 0, 0, 0]); // pLinear, reserved
            out.extend_from_slice(&i32s(&[*sampling, *sampling]));
        }
        out.push(0);
        out
    }

    /// The required channels as 32-bit floats.
    pub fn required_channels() -> Vec<u8> {
        channel_list(&REQUIRED.map(|n| (n, FLOAT, 1)))
    }

    /// The attributes of an uncompressed scan-line part of `w`×`h` with `channels`.
    pub fn scanline(w: i32, h: i32, channels: Vec<u8>) -> Vec<Vec<u8>> {
        let window = i32s(&[0, 0, w - 1, h - 1]);
        vec![
            attribute("channels", "chlist", &channels),
            attribute("compression", "compression", &[0]),
            attribute("dataWindow", "box2i", &window),
            attribute("displayWindow", "box2i", &window),
            attribute("lineOrder", "lineOrder", &[0]),
            attribute("pixelAspectRatio", "float", &1f32.to_le_bytes()),
            attribute("screenWindowCenter", "v2f", &[0; 8]),
            attribute("screenWindowWidth", "float", &1f32.to_le_bytes()),
        ]
    }

    /// A `tiledesc` value: one level, tiles of `w`×`h`.
    pub fn tiles(w: u32, h: u32) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(&w.to_le_bytes());
        out.extend_from_slice(&h.to_le_bytes());
        out.push(0);
        out
    }

    /// `attributes` without the one named `name`.
    pub fn without(mut attributes: Vec<Vec<u8>>, name: &str) -> Vec<Vec<u8>> {
        let prefix = format!("{name}\0");
        attributes.retain(|a| !a.starts_with(prefix.as_bytes()));
        attributes
    }

    /// `attributes` with the one named like `attribute` replaced (or added).
    pub fn with(attributes: Vec<Vec<u8>>, attribute: Vec<u8>) -> Vec<Vec<u8>> {
        let name = String::from_utf8_lossy(&attribute[..attribute.iter().position(|b| *b == 0).unwrap()]).to_string();
        let mut out = without(attributes, &name);
        out.push(attribute);
        out
    }

    pub fn header(attributes: &[Vec<u8>]) -> Vec<u8> {
        let mut out = attributes.concat();
        out.push(0);
        out
    }

    /// Magic number, version 2 with `flags`, the headers (ended by an empty header when
    /// multi-part), then `rest` (offset tables and chunks).
    pub fn file(flags: u32, headers: &[Vec<u8>], rest: &[u8]) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&(2 | flags).to_le_bytes());
        for h in headers {
            out.extend_from_slice(h);
        }
        if flags & MULTIPART != 0 {
            out.push(0);
        }
        out.extend_from_slice(rest);
        out
    }

    /// Where the header of a single-part file ends: the offset of its terminating 0.
    pub fn header_end(bytes: &[u8]) -> usize {
        let mut i = 8;
        let zero = |from: usize| from + bytes[from..].iter().position(|b| *b == 0).unwrap();
        while bytes[i] != 0 {
            i = zero(zero(i) + 1) + 1;
            let size = i32::from_le_bytes(bytes[i..i + 4].try_into().unwrap());
            i += 4 + size as usize;
        }
        i
    }

    /// The offset table of a single-part file of `chunks` chunks.
    pub fn offsets(bytes: &[u8], chunks: usize) -> Vec<u64> {
        let start = header_end(bytes) + 1;
        (0..chunks).map(|i| u64::from_le_bytes(bytes[start + 8 * i..start + 8 * i + 8].try_into().unwrap())).collect()
    }

    /// Sets entry `index` of the offset table of a single-part file.
    pub fn set_offset(bytes: &mut [u8], index: usize, value: u64) {
        let at = header_end(bytes) + 1 + 8 * index;
        bytes[at..at + 8].copy_from_slice(&value.to_le_bytes());
    }

    /// Adds `attribute` at the end of the header of a single-part file of `chunks` chunks,
    /// moving the offsets along.
    pub fn insert_attribute(bytes: &[u8], chunks: usize, attribute: &[u8]) -> Vec<u8> {
        let end = header_end(bytes);
        let table = offsets(bytes, chunks);
        let mut out = bytes[..end].to_vec();
        out.extend_from_slice(attribute);
        out.extend_from_slice(&bytes[end..]);
        for (i, offset) in table.iter().enumerate() {
            set_offset(&mut out, i, offset + attribute.len() as u64);
        }
        out
    }
}

fn channels(planes: &[(String, Vec<f32>)], sample: Sample) -> AnyChannels<FlatSamples> {
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> = planes
        .iter()
        .map(|(n, d)| {
            let samples = match sample {
                Sample::F32 => FlatSamples::F32(d.clone()),
                Sample::F16 => FlatSamples::F16(d.iter().map(|v| f16::from_f32(*v)).collect()),
            };
            AnyChannel::new(n.as_str(), samples)
        })
        .collect();
    AnyChannels::sort(list)
}

/// Writes in one thread: the chunk order of a parallel write may vary, the corpus must not.
fn write_image(image: Image<exr::image::Layers<AnyChannels<FlatSamples>>>) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    image.write().non_parallel().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// `planes` as one part with `encoding`.
fn encode(w: usize, h: usize, planes: &[(String, Vec<f32>)], encoding: Encoding, sample: Sample) -> Vec<u8> {
    write_image(Image::from_layers(
        ImageAttributes::new(IntegerBounds::from_dimensions((w, h))),
        smallvec::smallvec![Layer::new((w, h), LayerAttributes::default(), encoding, channels(planes, sample))],
    ))
}

/// Scan lines in blocks of 16, ZIP: an 8×8 frame is one chunk, an 8×32 frame two.
const ZIP16: Encoding =
    Encoding { compression: Compression::ZIP16, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };

/// RLE tiles of 64×64 (the helpers' encoding), in increasing order.
const RLE_TILES: Encoding =
    Encoding { compression: Compression::RLE, blocks: Blocks::Tiles(Vec2(64, 64)), line_order: LineOrder::Increasing };

/// The frame's planes with `f` applied to sample `i` of channel `name` (`f(i, &mut v)`).
fn with_values(
    mut planes: Vec<(String, Vec<f32>)>,
    name: &str,
    f: impl Fn(usize, &mut f32),
) -> Vec<(String, Vec<f32>)> {
    let plane = &mut planes.iter_mut().find(|(n, _)| n == name).unwrap_or_else(|| panic!("no {name}")).1;
    plane.iter_mut().enumerate().for_each(|(i, v)| f(i, v));
    planes
}

/// An `S`×`S` frame (float32, in one tile) whose samples `edit` changes.
fn frame_with(edit: impl FnOnce(Vec<(String, Vec<f32>)>) -> Vec<(String, Vec<f32>)>) -> Vec<u8> {
    exr_single(S, S, &edit(named_planes(S, S, false)), Sample::F32)
}

/// An `S`×`S` frame of the channels `keep` accepts.
fn frame_of_channels(keep: impl Fn(&str) -> bool) -> Vec<u8> {
    frame_with(|planes| planes.into_iter().filter(|(n, _)| keep(n)).collect())
}

/// A multi-part frame: one part per buffer (`diffuse.R` is channel `R` of part `diffuse`),
/// each `S`×`S` except those listed in `sizes`, changed by `edit(part, planes)`.
fn multi_part(sizes: &[(&str, (usize, usize))], edit: impl Fn(&str, &mut Vec<(String, Vec<f32>)>)) -> Vec<u8> {
    let layers: exr::image::Layers<_> = common::by_part(&named_planes(S, S, false))
        .into_iter()
        .map(|(part, mut planes)| {
            let size = sizes.iter().find(|(p, _)| *p == part).map_or((S, S), |(_, s)| *s);
            for (_, d) in planes.iter_mut() {
                d.resize(size.0 * size.1, 0.5);
            }
            edit(&part, &mut planes);
            let attributes = LayerAttributes::named(part.as_str());
            Layer::new(size, attributes, Encoding::FAST_LOSSLESS, channels(&planes, Sample::F32))
        })
        .collect();
    write_image(Image::from_layers(ImageAttributes::new(IntegerBounds::from_dimensions((S, S))), layers))
}

/// A copy of `bytes` changed by `edit`.
fn edited(bytes: &[u8], edit: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut b = bytes.to_vec();
    edit(&mut b);
    b
}

/// A single-part file of one header and nothing after it (for files refused from the header).
fn header_only(attributes: &[Vec<u8>]) -> Vec<u8> {
    raw::file(0, &[raw::header(attributes)], &[])
}

/// The attributes of an `S`×`S` uncompressed part with these channels.
fn small_part(channels: &[(&str, i32, i32)]) -> Vec<Vec<u8>> {
    raw::scanline(S as i32, S as i32, raw::channel_list(channels))
}

/// The required channels as floats, each sampled every `sampling(name)` pixels.
fn required_sampled(sampling: impl Fn(&str) -> i32) -> Vec<(&'static str, i32, i32)> {
    raw::REQUIRED.iter().map(|n| (*n, raw::FLOAT, sampling(n))).collect()
}

/// Every file of the corpus, by name.
fn corpus_files() -> Vec<(&'static str, Vec<u8>)> {
    use raw::*;
    let good = frame(S, S);
    // ZIP scan lines: one chunk for 8 lines, two for 32.
    let zip = encode(S, S, &named_planes(S, S, false), ZIP16, Sample::F32);
    let zip_tall = encode(S, 32, &named_planes(S, 32, false), ZIP16, Sample::F32);
    let zip_chunk = offsets(&zip, 1)[0] as usize;
    let required = required_sampled(|_| 1);
    let small = small_part(&required);
    let with_note = |size: i32| [small.clone(), vec![attribute_sized("note", "string", size, b"hello")]].concat();

    vec![
        // Building blocks of other cases.
        ("good-8x8.exr", good.clone()),
        ("reference-8x8.exr", reference(S, S)),
        ("reference-8x4.exr", reference(S, 4)),
        ("reference-albedo-only.exr", frame_of_channels(|n| n.starts_with("albedo."))),
        // Not an EXR, truncated, broken structure.
        ("not-an-exr.txt", b"this is not an EXR file, just some text\n".to_vec()),
        ("png-signature.png", [&b"\x89PNG\r\n\x1a\n"[..], &[0u8; 56]].concat()),
        ("magic-one-byte-off.exr", edited(&good, |b| b[3] = 0x02)),
        ("truncated-magic-only.exr", good[..4].to_vec()),
        ("truncated-in-header.exr", good[..100].to_vec()),
        ("truncated-in-offset-table.exr", good[..header_end(&good) + 4].to_vec()),
        ("truncated-pixel-data.exr", good[..good.len() * 2 / 3].to_vec()),
        ("truncated-last-byte.exr", good[..good.len() - 1].to_vec()),
        ("version-3.exr", edited(&good, |b| b[4] = 3)),
        ("unknown-feature-flag.exr", edited(&good, |b| b[6] |= 0x20)), // bit 21
        ("tiled-and-multipart-flags.exr", file(TILED | MULTIPART, &[header(&small)], &[])),
        ("no-channels-attribute.exr", header_only(&without(small.clone(), "channels"))),
        ("no-data-window.exr", header_only(&without(small.clone(), "dataWindow"))),
        ("no-compression-attribute.exr", header_only(&without(small.clone(), "compression"))),
        ("unknown-compression.exr", header_only(&with(small.clone(), attribute("compression", "compression", &[42])))),
        ("unknown-pixel-type.exr", header_only(&small_part(&raw::REQUIRED.map(|n| (n, 7, 1))))),
        (
            "data-window-beyond-int-range.exr",
            header_only(&with(small.clone(), attribute("dataWindow", "box2i", &i32s(&[0, 0, i32::MAX - 1, 7])))),
        ),
        ("attribute-size-negative.exr", header_only(&with_note(-5))),
        ("attribute-size-2gb.exr", header_only(&with_note(i32::MAX))),
        // The channels attribute, then 300 bytes of a name that never ends.
        ("attribute-name-unterminated.exr", file(0, &[[small[0].clone(), vec![b'x'; 300]].concat()], &[])),
        // Absurd declared sizes: a few hundred bytes that declare a huge image, with the
        // first bytes of its offset table.
        (
            "bomb-1000000x1000000.exr",
            file(0, &[header(&scanline(1_000_000, 1_000_000, channel_list(&required)))], &[0; 64]),
        ),
        ("bomb-4000000x1.exr", file(0, &[header(&scanline(4_000_000, 1, channel_list(&required)))], &[0; 64])),
        ("bomb-tiled-100000x100000-in-1x1-tiles.exr", {
            let mut a = scanline(100_000, 100_000, channel_list(&required));
            a.push(attribute("tiles", "tiledesc", &tiles(1, 1)));
            file(TILED, &[header(&a)], &[0; 64])
        }),
        ("bomb-multipart-second-part.exr", {
            let beauty = part_header(scanline(S as i32, S as i32, channel_list(&required)), "main", "scanlineimage");
            let huge =
                part_header(scanline(1_000_000, 1_000_000, channel_list(&[("Y", FLOAT, 1)])), "huge", "scanlineimage");
            file(MULTIPART, &[beauty, huge], &[0; 64])
        }),
        (
            "bomb-chunk-count-attribute.exr",
            insert_attribute(&zip, 1, &attribute("chunkCount", "int", &i32::MAX.to_le_bytes())),
        ),
        // A chunk is y (i32), its byte count (i32), its bytes.
        (
            "bomb-chunk-size-2gb.exr",
            edited(&zip, |b| b[zip_chunk + 4..zip_chunk + 8].copy_from_slice(&i32::MAX.to_le_bytes())),
        ),
        ("bomb-zip-chunk-inflates-to-2mb.exr", {
            // The one chunk of a 2048×16 frame of zeros (2.4 MB once inflated) in the place of
            // the chunk of an 8×8 frame (4.6 kB).
            let zeros: Vec<_> =
                named_planes(S, S, false).into_iter().map(|(n, _)| (n, vec![0f32; 2048 * 16])).collect();
            let big = encode(2048, 16, &zeros, ZIP16, Sample::F32);
            let payload = &big[offsets(&big, 1)[0] as usize + 8..];
            let mut b = zip[..zip_chunk].to_vec();
            b.extend_from_slice(&0i32.to_le_bytes());
            b.extend_from_slice(&(payload.len() as i32).to_le_bytes());
            b.extend_from_slice(payload);
            b
        }),
        // Corrupt offset tables and chunks.
        ("offset-table-past-eof.exr", edited(&zip, |b| set_offset(b, 0, 1 << 40))),
        ("offset-table-duplicate.exr", edited(&zip_tall, |b| set_offset(b, 1, offsets(&zip_tall, 2)[0]))),
        (
            "chunk-y-out-of-range.exr",
            edited(&zip, |b| b[zip_chunk..zip_chunk + 4].copy_from_slice(&4096i32.to_le_bytes())),
        ),
        ("pixel-data-corrupt.exr", edited(&zip, |b| b.iter_mut().rev().take(40).for_each(|x| *x ^= 0x5a))),
        // Channels and layers.
        ("missing-depth.exr", frame_without(S, S, "depth")),
        ("missing-albedo-and-normal.exr", frame_of_channels(|n| !n.starts_with("albedo") && !n.starts_with("normal"))),
        ("missing-diffuse-g.exr", frame_of_channels(|n| n != "diffuse.G")),
        ("beauty-rgb-only.exr", reference(S, S)),
        ("empty-channel-list.exr", header_only(&small_part(&[]))),
        ("duplicate-channel.exr", header_only(&small_part(&[required.clone(), vec![("depth.Z", FLOAT, 1)]].concat()))),
        (
            "duplicate-channel-across-parts.exr",
            multi_part(&[], |part, planes| {
                if part == "diffuse" {
                    planes.push(("diffuse.R".into(), vec![0.0; S * S]));
                }
            }),
        ),
        ("subsampled-channel.exr", header_only(&small_part(&required_sampled(|n| if n == "depth.Z" { 2 } else { 1 })))),
        ("part-sizes-differ.exr", multi_part(&[("specular", (16, 8))], |_, _| {})),
        ("part-origins-differ.exr", {
            let mut image = common::read_exr(&multi_part(&[], |_, _| {}));
            image.layer_data[1].attributes.layer_position = exr::prelude::Vec2(0, -2);
            write_image(image)
        }),
        ("channels-unsorted.exr", header_only(&small_part(&required.iter().rev().copied().collect::<Vec<_>>()))),
        // Values.
        (
            "nan-in-diffuse.exr",
            frame_with(|p| {
                with_values(p, "diffuse.G", |i, v| {
                    if i % 13 == 0 {
                        *v = f32::NAN
                    }
                })
            }),
        ),
        (
            "inf-in-specular-and-depth.exr",
            frame_with(|p| {
                let p = with_values(p, "specular.R", |i, v| {
                    if i < 3 {
                        *v = f32::INFINITY
                    }
                });
                with_values(p, "depth.Z", |i, v| {
                    if i >= 62 {
                        *v = f32::NEG_INFINITY
                    }
                })
            }),
        ),
        (
            "negative-values.exr",
            frame_with(|p| {
                with_values(with_values(p, "diffuse.R", |_, v| *v = -*v - 1.0), "depth.Z", |_, v| *v = -5.0)
            }),
        ),
        (
            "huge-values.exr",
            frame_with(|p| with_values(with_values(p, "diffuse.R", |_, v| *v = 3e38), "specular.G", |_, v| *v = 3e38)),
        ),
        (
            "f16-overflow-to-inf.exr",
            exr_single(
                S,
                S,
                &with_values(named_planes(S, S, false), "albedo.B", |i, v| {
                    if i < 10 {
                        *v = 1e6
                    }
                }),
                Sample::F16,
            ),
        ),
        ("all-nan.exr", frame_with(|p| p.into_iter().map(|(n, d)| (n, vec![f32::NAN; d.len()])).collect())),
        ("no-variances.exr", frame_of_channels(|n| !n.contains("Variance"))),
        ("tiny-1x1.exr", frame(1, 1)),
        // Tiled and deep.
        (
            "tiled-4x4-tiles.exr",
            encode(
                S,
                S,
                &named_planes(S, S, false),
                Encoding { blocks: Blocks::Tiles(Vec2(4, 4)), ..RLE_TILES },
                Sample::F32,
            ),
        ),
        ("deep-scanline.exr", deep_file(false)),
        ("deep-tiled.exr", deep_file(true)),
        ("deep-part-in-multipart.exr", {
            let beauty = part_header(scanline(S as i32, S as i32, channel_list(&required)), "beauty", "scanlineimage");
            file(MULTIPART | DEEP, &[beauty, deep_header(false, "samples")], &[0; 64])
        }),
        // HTTP.
        ("options-70kb.json", format!("{{\"label\": \"{}\"}}", "x".repeat(70_000)).into_bytes()),
    ]
}

/// The header of a part of a multi-part file: `attributes` with its name and type, and
/// the chunk count of an uncompressed scan-line part.
fn part_header(mut attributes: Vec<Vec<u8>>, name: &str, kind: &str) -> Vec<u8> {
    use raw::attribute;
    let window = attributes.iter().find(|a| a.starts_with(b"dataWindow\0")).expect("a data window").clone();
    let y_max = i32::from_le_bytes(window[window.len() - 4..].try_into().unwrap());
    attributes.push(attribute("name", "string", name.as_bytes()));
    attributes.push(attribute("type", "string", kind.as_bytes()));
    attributes.push(attribute("chunkCount", "int", &(y_max + 1).to_le_bytes()));
    raw::header(&attributes)
}

/// A single-part deep file: the header only (a deep file is refused from its header), with
/// an offset table of zeros.
fn deep_file(tiled: bool) -> Vec<u8> {
    raw::file(raw::DEEP, &[deep_header(tiled, "deep")], &[0; 64])
}

/// The header of a deep scan-line or deep tiled part named `name`.
fn deep_header(tiled: bool, name: &str) -> Vec<u8> {
    use raw::*;
    let mut a = scanline(S as i32, S as i32, required_channels());
    a.push(attribute("name", "string", name.as_bytes()));
    a.push(attribute("type", "string", if tiled { b"deeptile" } else { b"deepscanline" }));
    a.push(attribute("version", "int", &1i32.to_le_bytes()));
    a.push(attribute("maxSamplesPerPixel", "int", &4i32.to_le_bytes()));
    a.push(attribute("chunkCount", "int", &(if tiled { 1i32 } else { 8 }).to_le_bytes()));
    if tiled {
        a.push(attribute("tiles", "tiledesc", &tiles(8, 8)));
    }
    header(&a)
}

#[test]
#[ignore = "rewrites tests/bad-inputs/ from the generator"]
fn regenerate_corpus() {
    let dir = corpus_dir();
    std::fs::create_dir_all(&dir).unwrap();
    for (name, bytes) in corpus_files() {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
}

// --- The manifest --------------------------------------------------------------------------

/// One case of `cases.json`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Case {
    name: String,
    /// One line: what the input is and why it is refused.
    what: String,
    transport: Transport,
    http: Option<HttpRequest>,
    /// The messages of a `SubmitJob` stream, in order.
    grpc: Option<Vec<GrpcMessage>>,
    expect: Expect,
    /// A defect outside the EXR reader: the case says what should happen, and the test warns
    /// instead of failing while the daemon does otherwise.
    known_defect: Option<String>,
}

#[derive(Deserialize, Clone, Copy, PartialEq, Debug)]
#[serde(rename_all = "lowercase")]
enum Transport {
    Http,
    Grpc,
}

/// Bytes: a corpus file (or the bytes `from..to` of it), inline text, or that many zeros;
/// nothing at all when none is given.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct Data {
    file: Option<String>,
    from: Option<usize>,
    to: Option<usize>,
    text: Option<String>,
    zeros: Option<usize>,
}

impl Data {
    fn load(&self) -> Vec<u8> {
        match (&self.file, &self.text, self.zeros) {
            (Some(file), None, None) => {
                let bytes = read_corpus(file);
                bytes[self.from.unwrap_or(0)..self.to.unwrap_or(bytes.len())].to_vec()
            }
            (None, Some(text), None) => text.clone().into_bytes(),
            (None, None, Some(n)) => vec![0; n],
            (None, None, None) => Vec::new(),
            _ => panic!("give one of file, text and zeros"),
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct HttpRequest {
    /// A raw body (ignored with `multipart`).
    #[serde(default)]
    body: Data,
    /// A multipart/form-data body of these parts, in this order.
    multipart: Option<Vec<FormPart>>,
    /// Default: `image/x-exr`, or multipart/form-data with the body's boundary.
    content_type: Option<String>,
    /// Without the `?`.
    #[serde(default)]
    query: String,
    #[serde(default)]
    headers: Vec<(String, String)>,
    /// Streamed without a Content-Length.
    #[serde(default)]
    chunked: bool,
    /// Only the first `cut_at` bytes of the body are sent.
    cut_at: Option<usize>,
}

#[derive(Deserialize)]
struct FormPart {
    name: String,
    #[serde(flatten)]
    data: Data,
}

#[derive(Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
enum GrpcMessage {
    Header {
        #[serde(default)]
        options: GrpcOptions,
        frame_size: Size,
        #[serde(default)]
        reference_size: Size,
    },
    Chunk(GrpcChunk),
    /// A message with neither a header nor a chunk.
    Neither,
}

#[derive(Deserialize)]
struct GrpcChunk {
    part: ChunkPart,
    #[serde(flatten)]
    data: Data,
}

/// `FRAME`, `REFERENCE`, `UNSPECIFIED`, or a raw enum value.
#[derive(Deserialize)]
#[serde(untagged)]
enum ChunkPart {
    Name(String),
    Value(i32),
}

/// `pb::JobOptions` with raw enum values.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
struct GrpcOptions {
    priority: i32,
    layers: Vec<String>,
    idempotency_key: String,
    label: String,
    variant: i32,
    deadline_seconds: u64,
    variant_name: String,
}

/// A declared size: bytes, or the size of a corpus file less `minus`.
#[derive(Deserialize)]
#[serde(untagged)]
enum Size {
    Bytes(u64),
    Of {
        size_of: String,
        #[serde(default)]
        minus: u64,
    },
}

impl Default for Size {
    fn default() -> Self {
        Size::Bytes(0)
    }
}

impl Size {
    fn bytes(&self) -> u64 {
        match self {
            Size::Bytes(n) => *n,
            Size::Of { size_of, minus } => read_corpus(size_of).len() as u64 - minus,
        }
    }
}

/// What must happen. Messages are substrings of the error message.
#[derive(Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
enum Expect {
    /// Refused over HTTP: status, `error.code`, message.
    HttpError { status: u16, code: String, message: String },
    /// Refused over gRPC: the code as tonic spells it (`InvalidArgument`), message.
    GrpcError { code: String, message: String },
    /// Accepted (the header is valid), then the job fails: `error.code`, message.
    JobFails { code: String, message: String },
    /// Accepted and denoised: the job's JSON has `json` (pointer → value), and the result is
    /// a finite image of the frame's size.
    Succeeds {
        #[serde(default)]
        json: Vec<(String, Value)>,
    },
}

impl Expect {
    fn kind(&self) -> &'static str {
        match self {
            Expect::HttpError { .. } => "rejected over HTTP",
            Expect::GrpcError { .. } => "rejected over gRPC",
            Expect::JobFails { .. } => "accepted then failed",
            Expect::Succeeds { .. } => "succeeded",
        }
    }
}

fn read_corpus(name: &str) -> Vec<u8> {
    let path = corpus_dir().join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn load_cases() -> Vec<Case> {
    let text = read_corpus("cases.json");
    let cases: Vec<Case> = serde_json::from_slice(&text).unwrap_or_else(|e| panic!("cases.json: {e}"));
    let mut names = BTreeSet::new();
    for c in &cases {
        assert!(names.insert(c.name.as_str()), "two cases are named {}", c.name);
        assert!(!c.what.is_empty(), "{}: say what the case is", c.name);
        let fits = match c.transport {
            Transport::Http => c.http.is_some() && c.grpc.is_none() && !matches!(c.expect, Expect::GrpcError { .. }),
            Transport::Grpc => c.grpc.is_some() && c.http.is_none() && !matches!(c.expect, Expect::HttpError { .. }),
        };
        assert!(fits, "{}: the request and the expectation must match the transport", c.name);
    }
    cases
}

/// The corpus files a case reads.
fn files_of(case: &Case) -> Vec<String> {
    let mut data: Vec<&Data> = Vec::new();
    let mut out = Vec::new();
    if let Some(r) = &case.http {
        data.push(&r.body);
        data.extend(r.multipart.iter().flatten().map(|p| &p.data));
    }
    for m in case.grpc.iter().flatten() {
        match m {
            GrpcMessage::Header { frame_size, reference_size, .. } => {
                for s in [frame_size, reference_size] {
                    if let Size::Of { size_of, .. } = s {
                        out.push(size_of.clone());
                    }
                }
            }
            GrpcMessage::Chunk(c) => data.push(&c.data),
            GrpcMessage::Neither => {}
        }
    }
    out.extend(data.into_iter().filter_map(|d| d.file.clone()));
    out
}

// --- Sending -------------------------------------------------------------------------------

/// What the daemon answered to a submission.
enum Answer {
    /// Status, JSON body.
    Http(StatusCode, Value),
    /// The job id, or the refusal.
    Grpc(Result<String, Box<tonic::Status>>),
    /// No answer: the connection failed or the call hung.
    None(String),
}

impl Answer {
    /// The job the submission created, if it created one.
    fn accepted(&self) -> Option<String> {
        match self {
            Answer::Http(StatusCode::ACCEPTED, job) => job["id"].as_str().map(str::to_owned),
            Answer::Grpc(Ok(id)) => Some(id.clone()),
            _ => None,
        }
    }

    fn describe(&self) -> String {
        match self {
            Answer::Http(status, body) => format!("HTTP {status} {body}"),
            Answer::Grpc(Ok(id)) => format!("gRPC OK, job {id}"),
            Answer::Grpc(Err(s)) => format!("gRPC {:?}: {}", s.code(), s.message()),
            Answer::None(why) => format!("no answer: {why}"),
        }
    }
}

const BOUNDARY: &str = "bad-inputs-boundary-4kTQ1tWz";

/// A multipart/form-data body of `parts`, in order: (content type, body).
fn form_data(parts: &[FormPart]) -> (String, Vec<u8>) {
    let mut body = Vec::new();
    for part in parts {
        let (filename, content_type) = match part.name.as_str() {
            "options" => (String::new(), "application/json"),
            name => (format!("; filename=\"{name}.exr\""), "image/x-exr"),
        };
        body.extend_from_slice(
            format!(
                "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{}\"{filename}\r\nContent-Type: {content_type}\r\n\r\n",
                part.name
            )
            .as_bytes(),
        );
        body.extend_from_slice(&part.data.load());
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={BOUNDARY}"), body)
}

/// A body streamed in 64 KiB frames, without a Content-Length.
fn chunked(bytes: Vec<u8>) -> http_body_util::combinators::BoxBody<Bytes, std::io::Error> {
    let frames: Vec<Result<BodyFrame<Bytes>, std::io::Error>> =
        bytes.chunks(64 * 1024).map(|c| Ok(BodyFrame::data(Bytes::copy_from_slice(c)))).collect();
    BodyExt::boxed(StreamBody::new(futures_util::stream::iter(frames)))
}

async fn send_http(d: &Daemon, r: &HttpRequest) -> Answer {
    let (default_type, mut body) = match &r.multipart {
        Some(parts) => form_data(parts),
        None => ("image/x-exr".to_string(), r.body.load()),
    };
    if let Some(n) = r.cut_at {
        body.truncate(n);
    }
    let content_type = r.content_type.clone().unwrap_or(default_type);
    let mut headers: Vec<(&str, &str)> = r.headers.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    headers.push(("content-type", &content_type));
    let body = if r.chunked { chunked(body) } else { body_bytes(body) };
    http_answer(d.http.send(Method::POST, &format!("/v1/jobs?{}", r.query), &headers, body).await).await
}

async fn http_answer(response: anyhow::Result<hyper::Response<hyper::body::Incoming>>) -> Answer {
    let response = match response {
        Ok(r) => r,
        Err(e) => return Answer::None(e.to_string()),
    };
    match read_json(response).await {
        Ok((status, json)) => Answer::Http(status, json),
        Err(e) => Answer::None(format!("reading the answer: {e}")),
    }
}

fn grpc_message(m: &GrpcMessage) -> pb::SubmitJobRequest {
    use pb::submit_job_request::Message;
    let message = match m {
        GrpcMessage::Header { options: o, frame_size, reference_size } => Some(Message::Header(pb::SubmitHeader {
            options: Some(pb::JobOptions {
                priority: o.priority,
                layers: o.layers.clone(),
                idempotency_key: o.idempotency_key.clone(),
                label: o.label.clone(),
                variant: o.variant,
                deadline_seconds: o.deadline_seconds,
                variant_name: o.variant_name.clone(),
                ..Default::default()
            }),
            frame_size: frame_size.bytes(),
            reference_size: reference_size.bytes(),
        })),
        GrpcMessage::Chunk(c) => {
            let part = match &c.part {
                ChunkPart::Name(n) => {
                    pb::Part::from_str_name(&format!("PART_{n}")).unwrap_or_else(|| panic!("unknown part {n}")) as i32
                }
                ChunkPart::Value(v) => *v,
            };
            Some(Message::Chunk(pb::Chunk { part, data: c.data.load() }))
        }
        GrpcMessage::Neither => None,
    };
    pb::SubmitJobRequest { message }
}

async fn send_grpc(d: &Daemon, messages: &[GrpcMessage]) -> Answer {
    // No client-side limit on message sizes: the daemon's limit is under test.
    let mut client = grpc_connect(&d.grpc, None).await.expect("connect").max_encoding_message_size(usize::MAX);
    let stream = futures_util::stream::iter(messages.iter().map(grpc_message).collect::<Vec<_>>());
    Answer::Grpc(client.submit_job(stream).await.map(|r| r.into_inner().id).map_err(Box::new))
}

async fn send(d: &Daemon, case: &Case) -> Answer {
    let sending = async {
        match (&case.http, &case.grpc) {
            (Some(r), _) => send_http(d, r).await,
            (_, Some(m)) => send_grpc(d, m).await,
            _ => unreachable!("checked by load_cases"),
        }
    };
    tokio::time::timeout(Duration::from_secs(30), sending).await.unwrap_or(Answer::None("no answer in 30 s".into()))
}

// --- Checking ------------------------------------------------------------------------------

fn expect_eq<T: PartialEq + std::fmt::Debug>(what: &str, got: T, expected: T) -> Result<(), String> {
    if got == expected {
        Ok(())
    } else {
        Err(format!("{what} is {got:?}, expected {expected:?}"))
    }
}

fn expect_contains(what: &str, text: &str, part: &str) -> Result<(), String> {
    if text.contains(part) {
        Ok(())
    } else {
        Err(format!("{what} `{text}` does not contain `{part}`"))
    }
}

/// Waits until the job has finished (30 s at most).
async fn finished(d: &Daemon, id: &str) -> Result<Value, String> {
    tokio::time::timeout(Duration::from_secs(30), d.wait_finished(id))
        .await
        .map_err(|_| format!("job {id} did not finish in 30 s"))
}

/// The result of a succeeded job is a finite image of the job's size.
async fn check_result(d: &Daemon, job: &Value) -> Result<(), String> {
    let (status, bytes) = d.result(job["id"].as_str().unwrap_or_default()).await;
    expect_eq("the result's HTTP status", status, StatusCode::OK)?;
    let out = mcdenoise::frame::Frame::reference_from_exr_bytes(&bytes, &Default::default())
        .map_err(|e| format!("the result does not decode: {e}"))?;
    expect_eq(
        "the result's size",
        (out.width as u64, out.height as u64),
        (job["width"].as_u64().unwrap_or(0), job["height"].as_u64().unwrap_or(0)),
    )?;
    let bad = out.color().iter().flatten().filter(|v| !v.is_finite()).count();
    expect_eq("the count of non-finite samples in the result", bad, 0)
}

async fn check(d: &Daemon, expect: &Expect, answer: &Answer) -> Result<(), String> {
    match (expect, answer) {
        (Expect::HttpError { status, code, message }, Answer::Http(got, body)) => {
            expect_eq("the status", got.as_u16(), *status)?;
            expect_eq("error.code", body["error"]["code"].as_str(), Some(code.as_str()))?;
            expect_contains("error.message", body["error"]["message"].as_str().unwrap_or_default(), message)?;
            Ok(())
        }
        (Expect::GrpcError { code, message }, Answer::Grpc(Err(s))) => {
            expect_eq("the gRPC code", format!("{:?}", s.code()), code.clone())?;
            expect_contains("the gRPC message", s.message(), message)
        }
        (Expect::JobFails { code, message }, answer) => {
            let id = answer.accepted().ok_or_else(|| format!("expected 202 / OK, got {}", answer.describe()))?;
            let job = finished(d, &id).await?;
            expect_eq("the job's state", job["state"].as_str(), Some("failed"))?;
            expect_eq("the job's error.code", job["error"]["code"].as_str(), Some(code.as_str()))?;
            expect_contains("the job's error.message", job["error"]["message"].as_str().unwrap_or_default(), message)
        }
        (Expect::Succeeds { json }, answer) => {
            let id = answer.accepted().ok_or_else(|| format!("expected 202 / OK, got {}", answer.describe()))?;
            let job = finished(d, &id).await?;
            expect_eq("the job's state", job["state"].as_str(), Some("succeeded"))
                .map_err(|e| format!("{e}: {job}"))?;
            for (pointer, value) in json {
                expect_eq(&format!("job{pointer}"), job.pointer(pointer), Some(value))?;
            }
            check_result(d, &job).await
        }
        (_, answer) => Err(format!("unexpected answer: {}", answer.describe())),
    }
}

/// Submits a good 32×32 frame over `transport` (HTTP through `http`) and waits for it to
/// succeed; its job id.
async fn serve_a_good_job(d: &Daemon, http: &HttpClient, transport: Transport, good: &Path) -> Result<String, String> {
    let answer = match transport {
        Transport::Http => {
            let body = body_bytes(std::fs::read(good).unwrap());
            http_answer(http.send(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body).await).await
        }
        Transport::Grpc => {
            let mut client = grpc_connect(&d.grpc, None).await.map_err(|e| e.to_string())?;
            let upload = upload_stream(Default::default(), good, None, 16 * 1024).await.unwrap();
            Answer::Grpc(client.submit_job(upload).await.map(|r| r.into_inner().id).map_err(Box::new))
        }
    };
    let id = answer.accepted().ok_or_else(|| answer.describe())?;
    let job = finished(d, &id).await?;
    expect_eq("its state", job["state"].as_str(), Some("succeeded"))?;
    Ok(id)
}

/// Refused uploads leave no job and no files: the jobs listed and the job directories are
/// exactly the accepted ones, and no upload is left half-written.
fn check_no_leftovers(data_dir: &Path, listed: &BTreeSet<String>, accepted: &BTreeSet<String>) -> Vec<String> {
    let mut problems = Vec::new();
    if listed != accepted {
        problems.push(format!(
            "the daemon lists jobs that were not accepted {:?} or lacks accepted ones {:?}",
            listed.difference(accepted).collect::<Vec<_>>(),
            accepted.difference(listed).collect::<Vec<_>>()
        ));
    }
    for entry in std::fs::read_dir(data_dir.join("jobs")).unwrap().flatten() {
        let name = entry.file_name().to_string_lossy().to_string();
        if name.starts_with(mcdenoise::jobs::HEALTH_PROBE) {
            // The storage health check's own probe, written and removed on a blocking thread
            // that may still be finishing as the daemon stops.
            continue;
        }
        if !entry.path().is_dir() {
            problems.push(format!("a stray file is left in jobs/: {name}"));
            continue;
        }
        if !accepted.contains(&name) {
            problems.push(format!("a refused upload left the directory jobs/{name}"));
        }
        for file in std::fs::read_dir(entry.path()).unwrap().flatten() {
            if file.file_name().to_string_lossy().ends_with(".part") {
                problems.push(format!("a half-written upload is left: {}", file.path().display()));
            }
        }
    }
    problems
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bad_input_gets_its_specific_error_and_the_daemon_keeps_serving() {
    let t = Instant::now();
    let mut cases = load_cases();
    assert!(cases.len() >= 50, "the corpus has {} cases, at least 50 are wanted", cases.len());
    // BAD_INPUTS_ONLY=text runs only the cases whose name contains it.
    if let Ok(only) = std::env::var("BAD_INPUTS_ONLY") {
        cases.retain(|c| c.name.contains(&only));
        println!("BAD_INPUTS_ONLY={only}: {} cases", cases.len());
    }
    let data = tempfile::tempdir().unwrap();
    let scratch = tempfile::tempdir().unwrap();
    // Small limits keep the oversize cases cheap: 4096 pixels (the good frame has 1024),
    // 300 kB per upload (the good frame has about 75 kB).
    let d = start(data.path(), &["--max-pixels", "4096", "--max-body-bytes", "300000"]).await;
    d.ready().await;
    let good = write(scratch.path(), "good.exr", &frame(32, 32));

    let mut failures = Vec::new();
    let mut accepted = BTreeSet::new();
    let mut passed: Vec<&'static str> = Vec::new();
    let mut known_defects = 0;
    for case in &cases {
        let answer = send(&d, case).await;
        accepted.extend(answer.accepted());
        match (check(&d, &case.expect, &answer).await, &case.known_defect) {
            (Ok(()), None) => passed.push(case.expect.kind()),
            (Err(e), None) => failures.push(format!("{} ({}): {e}", case.name, case.what)),
            (Err(e), Some(defect)) => {
                known_defects += 1;
                println!("warning: {}: known defect, not checked: {defect}\n         got: {e}", case.name);
            }
            (Ok(()), Some(defect)) => {
                passed.push(case.expect.kind());
                println!("note: {}: now behaves as expected; remove its known_defect ({defect})", case.name);
            }
        }
        // The good job goes through the same client, on a kept-alive connection when the
        // daemon kept it open. After a known defect, a failure is a warning, and a fresh
        // connection must then be served.
        let mut served = serve_a_good_job(&d, &d.http, case.transport, &good).await;
        if let (Err(e), Some(defect)) = (&served, &case.known_defect) {
            println!("warning: after {}: known defect ({defect}): the good job right after failed: {e}", case.name);
            served = serve_a_good_job(&d, &HttpClient::new(&d.base, None), case.transport, &good).await;
        }
        match served {
            Ok(id) => {
                accepted.insert(id);
            }
            Err(e) => {
                failures.push(format!("after {}: a good job submitted right after was not served: {e}", case.name))
            }
        }
    }

    let (status, list) = d.get_json("/v1/jobs?limit=1000").await;
    assert_eq!(status, StatusCode::OK, "{list}");
    let listed: BTreeSet<String> =
        list["jobs"].as_array().unwrap().iter().filter_map(|j| j["id"].as_str().map(str::to_owned)).collect();
    // Checked once the daemon has stopped: while it runs, its storage health check writes
    // and removes a probe file in jobs/.
    d.stop().await;
    failures.extend(check_no_leftovers(data.path(), &listed, &accepted));

    let count = |kind: &str| passed.iter().filter(|k| **k == kind).count();
    println!(
        "{} cases: {} rejected over HTTP, {} over gRPC, {} accepted then failed, {} succeeded; {} known defects; {} failed ({:.1} s)",
        cases.len(),
        count("rejected over HTTP"),
        count("rejected over gRPC"),
        count("accepted then failed"),
        count("succeeded"),
        known_defects,
        failures.len(),
        t.elapsed().as_secs_f64()
    );
    assert!(failures.is_empty(), "{} problems:\n{}", failures.len(), failures.join("\n"));
    if let Ok(dir) = std::env::var("MCDENOISE_RELIABILITY_OUT") {
        let figures = serde_json::json!({
            "cases": cases.len(),
            "rejected_http": count("rejected over HTTP"),
            "rejected_grpc": count("rejected over gRPC"),
            "accepted_then_failed": count("accepted then failed"),
            "succeeded": count("succeeded"),
            "known_defects": known_defects,
            "good_jobs_after_cases_succeeded": cases.len(),
            "seconds": t.elapsed().as_secs_f64(),
        });
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(format!("{dir}/bad-inputs.json"), serde_json::to_string_pretty(&figures).unwrap()).unwrap();
    }
}

#[test]
fn the_corpus_is_what_the_generator_writes_and_holds_what_the_cases_use() {
    let generated = corpus_files();
    let mut names: BTreeSet<String> = BTreeSet::from(["cases.json".to_string(), "README.md".to_string()]);
    let mut total = 0;
    for (name, bytes) in &generated {
        let on_disk = read_corpus(name);
        assert!(on_disk == *bytes, "{name} is not what the generator writes: run `-- --ignored regenerate_corpus`");
        names.insert(name.to_string());
        total += bytes.len();
    }
    assert!(total < 1 << 20, "the corpus is {total} bytes; keep it under 1 MiB");
    let on_disk: BTreeSet<String> = std::fs::read_dir(corpus_dir())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .collect();
    assert_eq!(on_disk, names, "files in tests/bad-inputs/ that the generator does not write, or the reverse");
    for case in load_cases() {
        for file in files_of(&case) {
            assert!(names.contains(&file), "{}: no corpus file {file}", case.name);
        }
    }
}
