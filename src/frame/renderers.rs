//! Frames from renderers that do not write the canonical buffers, and frames without
//! variances.
//!
//! Blender Cycles writes passes as `<view layer>.<pass>.<channel>` and no diffuse/specular
//! split or variance. Its passes give the split exactly: diffuse = (Diffuse Direct +
//! Diffuse Indirect) × Diffuse Color, specular = Combined − diffuse (glossy, transmission,
//! emission, environment). [`recipes`] says, from the channel names alone, which canonical
//! channels can be derived and how, so that the daemon can validate a header before
//! decoding and [`derive`] can build the planes after.
//!
//! Variances a renderer does not write are taken as 0 (see `Frame::fill_missing_variances`).

use std::collections::BTreeMap;

use super::presets::ChannelMaps;
use super::{NamedPlanes, Plane};

/// How one canonical channel is computed from the file's channels.
#[derive(Clone, Debug, PartialEq)]
pub enum Recipe {
    /// The channel as it is.
    Copy(String),
    /// `(sum of terms) × factor`.
    Product { terms: Vec<String>, factor: String },
    /// `total − (sum of terms) × factor`.
    Remainder { total: String, terms: Vec<String>, factor: String },
    /// A channel of zeros.
    Zero,
    /// `Σ sign × channel` (a renderer preset's sums and remainders, [`super::presets`]).
    Signed(Vec<(f32, String)>),
}

impl Recipe {
    /// The file's channels the recipe reads.
    pub fn sources(&self) -> Vec<&str> {
        match self {
            Recipe::Copy(src) => vec![src.as_str()],
            Recipe::Product { terms, factor } => terms.iter().chain([factor]).map(String::as_str).collect(),
            Recipe::Remainder { total, terms, factor } => {
                [total].into_iter().chain(terms).chain([factor]).map(String::as_str).collect()
            }
            Recipe::Zero => Vec::new(),
            Recipe::Signed(terms) => terms.iter().map(|(_, n)| n.as_str()).collect(),
        }
    }
}

/// The channels of a file's beauty: the total radiance the denoised `R,G,B` replace, and
/// its alpha.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Beauty<'a> {
    /// `R,G,B`, else Cycles' `<view layer>.Combined.{R,G,B}`; empty when the file has
    /// neither (diffuse and specular only).
    pub color: Vec<&'a str>,
    /// `A`, else the `A` of Cycles' Combined pass.
    pub alpha: Option<&'a str>,
}

/// The beauty of a file with channels `names`.
pub fn beauty<'a>(names: &[&'a str]) -> Beauty<'a> {
    let has = |n: &str| names.contains(&n);
    let passes = passes(names);
    let combined = passes.get("Combined");
    let color = if ["R", "G", "B"].iter().all(|n| has(n)) {
        vec!["R", "G", "B"]
    } else {
        combined
            .and_then(|c| ["R", "G", "B"].iter().map(|ch| c.get(ch).copied()).collect::<Option<Vec<_>>>())
            .unwrap_or_default()
    };
    let alpha = names.iter().copied().find(|n| *n == "A").or_else(|| combined.and_then(|c| c.get("A").copied()));
    Beauty { color, alpha }
}

/// Cycles pass names, current and before Blender 5 (`DiffDir` ...).
const DIFFUSE_DIRECT: &[&str] = &["Diffuse Direct", "DiffDir"];
const DIFFUSE_INDIRECT: &[&str] = &["Diffuse Indirect", "DiffInd"];
const DIFFUSE_COLOR: &[&str] = &["Diffuse Color", "DiffCol"];

/// The channels of each pass: pass name → channel letter → full channel name. A name
/// `a.b.c` is pass `b`, channel `c` (view layer `a`, which may itself contain dots); with
/// several view layers the first in name order wins.
fn passes<'a>(names: &[&'a str]) -> BTreeMap<&'a str, BTreeMap<&'a str, &'a str>> {
    let mut sorted: Vec<&str> = names.to_vec();
    sorted.sort();
    let mut out: BTreeMap<&str, BTreeMap<&str, &str>> = BTreeMap::new();
    for name in sorted {
        let mut it = name.rsplitn(3, '.');
        let (Some(chan), Some(pass), Some(_layer)) = (it.next(), it.next(), it.next()) else { continue };
        out.entry(pass).or_default().entry(chan).or_insert(name);
    }
    out
}

/// The canonical channels that can be derived from `names` and how, for buffers the file
/// does not hold under a canonical or aliased name: from Cycles' passes, else through
/// `maps`. Empty for files in the canonical layout. A map the job chose is the only one
/// tried (Cycles' passes are then not looked for).
pub fn recipes(names: &[&str], maps: &ChannelMaps) -> Vec<(String, Recipe)> {
    let resolved = super::layout::resolve(names);
    let has = |b: super::Buffer| resolved[b as usize].is_some();
    let passes = if maps.chosen() { BTreeMap::new() } else { passes(names) };
    let pass = |candidates: &[&str], chans: &[&str]| -> Option<Vec<String>> {
        candidates.iter().find_map(|p| {
            let chs = passes.get(p)?;
            chans.iter().map(|c| chs.get(c).map(|n| n.to_string())).collect()
        })
    };
    let rgb = ["R", "G", "B"];
    let mut out = Vec::new();
    let mut add = |prefix: &str, suffixes: &[&str], recipes: Vec<Recipe>| add_to(&mut out, prefix, suffixes, recipes);

    if !has(super::Buffer::Diffuse) && !has(super::Buffer::Specular) {
        let combined = pass(&["Combined"], &rgb);
        let split = (pass(DIFFUSE_DIRECT, &rgb), pass(DIFFUSE_INDIRECT, &rgb), pass(DIFFUSE_COLOR, &rgb));
        match (combined, split) {
            (Some(total), (Some(dir), Some(ind), Some(col))) => {
                let terms = |c: usize| vec![dir[c].clone(), ind[c].clone()];
                add(
                    "diffuse",
                    &rgb,
                    (0..3).map(|c| Recipe::Product { terms: terms(c), factor: col[c].clone() }).collect(),
                );
                add(
                    "specular",
                    &rgb,
                    (0..3)
                        .map(|c| Recipe::Remainder { total: total[c].clone(), terms: terms(c), factor: col[c].clone() })
                        .collect(),
                );
            }
            // Without diffuse passes all light is treated as diffuse (divided by the albedo).
            (Some(total), _) => {
                add("diffuse", &rgb, total.iter().map(|n| Recipe::Copy(n.clone())).collect());
                add("specular", &rgb, vec![Recipe::Zero, Recipe::Zero, Recipe::Zero]);
            }
            _ => {}
        }
    }
    if !has(super::Buffer::Albedo) {
        if let Some(a) = pass(&["Denoising Albedo", "Albedo"], &rgb) {
            add("albedo", &rgb, a.into_iter().map(Recipe::Copy).collect());
        }
    }
    if !has(super::Buffer::Normal) {
        if let Some(n) = pass(&["Denoising Normal", "Normal"], &["X", "Y", "Z"]) {
            add("normal", &rgb, n.into_iter().map(Recipe::Copy).collect());
        }
    }
    if !has(super::Buffer::Depth) {
        if let Some(d) = pass(&["Denoising Depth", "Depth"], &["Z"]) {
            // Its background distance, 1e10, becomes "no hit" as every depth's does
            // (`layout::NO_HIT_DEPTH`).
            add("depth", &["Z"], d.into_iter().map(Recipe::Copy).collect());
        }
    }
    // Other renderers' AOV names (the channel maps), for what is still missing (not for
    // Cycles frames).
    let required = super::layout::REQUIRED;
    let derived = |b: super::Buffer, out: &[(String, Recipe)]| {
        has(b) || out.iter().any(|(n, _)| n.split('.').next() == Some(b.name()))
    };
    if !passes.contains_key("Combined") && required.iter().any(|b| !derived(*b, &out)) {
        if let Some((_, mapped)) = maps.recipes(names) {
            let keep: Vec<(String, Recipe)> = mapped
                .into_iter()
                .filter(|(n, _)| {
                    let base = n.split('.').next().unwrap_or("");
                    !super::Buffer::ALL.iter().any(|b| b.name() == base && derived(*b, &out))
                })
                .collect();
            out.extend(keep);
        }
    }
    // A beauty with albedo and normal but no split (what most renderers write by default):
    // the beauty in the diffuse slot, a zero specular and, if the file has none, a zero
    // depth ("no hit"), as the `beauty` variant takes them.
    let beauty = beauty(names);
    if beauty.color.len() == 3
        && !derived(super::Buffer::Diffuse, &out)
        && !derived(super::Buffer::Specular, &out)
        && derived(super::Buffer::Albedo, &out)
        && derived(super::Buffer::Normal, &out)
    {
        add_to(&mut out, "diffuse", &rgb, beauty.color.iter().map(|n| Recipe::Copy(n.to_string())).collect());
        add_to(&mut out, "specular", &rgb, vec![Recipe::Zero, Recipe::Zero, Recipe::Zero]);
        if !derived(super::Buffer::Depth, &out) {
            add_to(&mut out, "depth", &["Z"], vec![Recipe::Zero]);
        }
    }
    out
}

fn add_to(out: &mut Vec<(String, Recipe)>, prefix: &str, suffixes: &[&str], recipes: Vec<Recipe>) {
    for (s, r) in suffixes.iter().zip(recipes) {
        out.push((format!("{prefix}.{s}"), r));
    }
}

/// Whether a file with channels `names` has no diffuse/specular split, only a beauty (a
/// Cycles Combined pass without the Diffuse passes included): [`recipes`] then derives its
/// diffuse as the beauty and its specular as zero.
pub fn beauty_only(names: &[&str], maps: &ChannelMaps) -> bool {
    recipes(names, maps).iter().any(|(n, r)| n == "specular.R" && *r == Recipe::Zero)
}

/// What a job says when a frame without the diffuse/specular split ([`beauty_only`]) was
/// denoised by a variant other than `beauty`.
pub fn no_split_warning(variant: &str) -> String {
    format!(
        "the frame has no diffuse/specular split (a beauty only, or Cycles' Combined without the Diffuse Direct, \
         Indirect and Color passes) and `{variant}` denoised it with all light taken as diffuse (divided by the \
         albedo), so glossy highlights and reflections were denoised as texture; the `beauty` variant is made for \
         such frames, or write the split (Cycles: View Layer Properties > Passes > Light > Diffuse)"
    )
}

/// Why a frame that lacks required buffers lacks them, in its renderer's terms, when its
/// channels say which renderer or which kind of output it is, or in the terms of the map
/// the job chose.
pub fn hint(names: &[&str], maps: &ChannelMaps) -> Option<String> {
    if maps.chosen() {
        return maps.hint(names);
    }
    let all = with_derived(names, maps);
    let all: Vec<&str> = all.iter().map(String::as_str).collect();
    let resolved = super::layout::resolve(&all);
    let has = |b: super::Buffer| resolved[b as usize].is_some();
    use super::Buffer::{Albedo, Depth, Diffuse, Normal, Specular};
    let cycles = passes(names).contains_key("Combined");
    if cycles && !(has(Albedo) && has(Normal) && has(Depth)) {
        return Some(
            "a Blender Cycles frame needs the Denoising Data passes (albedo, normal, depth): enable View Layer \
             Properties > Passes > Data > Denoising Data"
                .into(),
        );
    }
    let no_split = beauty(names).color.len() == 3 && !has(Diffuse) && !has(Specular);
    maps.hint(names).or_else(|| {
        no_split.then(|| {
            "a frame with a beauty but no diffuse/specular split needs an albedo and a normal (then the `beauty` \
             variant takes it; depth is optional), or the diffuse and specular layers (docs/frame-layout.md)"
                .into()
        })
    })
}

/// `names` plus the canonical names [`recipes`] can derive.
pub fn with_derived(names: &[&str], maps: &ChannelMaps) -> Vec<String> {
    let mut all: Vec<String> = names.iter().map(|s| s.to_string()).collect();
    all.extend(recipes(names, maps).into_iter().map(|(n, _)| n));
    all
}

/// Appends the planes [`recipes`] derives from `planes`.
pub fn derive(planes: &mut NamedPlanes, len: usize, maps: &ChannelMaps) {
    let names: Vec<&str> = planes.iter().map(|(n, _)| n.as_str()).collect();
    let todo = recipes(&names, maps);
    if todo.is_empty() {
        return;
    }
    let index: BTreeMap<String, usize> = planes.iter().enumerate().map(|(i, (n, _))| (n.clone(), i)).collect();
    let get = |n: &String| -> &Plane { &planes[index[n]].1 };
    let sum = |terms: &[String]| -> Plane {
        let mut s = vec![0f32; len];
        for t in terms {
            for (a, b) in s.iter_mut().zip(get(t)) {
                *a += b;
            }
        }
        s
    };
    let derived: Vec<(String, Plane)> = todo
        .iter()
        .map(|(name, recipe)| {
            let plane = match recipe {
                Recipe::Copy(src) => get(src).clone(),
                Recipe::Product { terms, factor } => sum(terms).iter().zip(get(factor)).map(|(s, f)| s * f).collect(),
                Recipe::Remainder { total, terms, factor } => {
                    let d = sum(terms);
                    get(total).iter().zip(&d).zip(get(factor)).map(|((t, s), f)| t - s * f).collect()
                }
                Recipe::Zero => vec![0f32; len],
                Recipe::Signed(terms) => {
                    let mut s = vec![0f32; len];
                    for (sign, t) in terms {
                        for (a, b) in s.iter_mut().zip(get(t)) {
                            *a += sign * b;
                        }
                    }
                    s
                }
            };
            (name.clone(), plane)
        })
        .collect();
    planes.extend(derived);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycles_names_give_the_exact_split() {
        let names = [
            "ViewLayer.Combined.R",
            "ViewLayer.Combined.G",
            "ViewLayer.Combined.B",
            "ViewLayer.Combined.A",
            "ViewLayer.Diffuse Direct.R",
            "ViewLayer.Diffuse Direct.G",
            "ViewLayer.Diffuse Direct.B",
            "ViewLayer.Diffuse Indirect.R",
            "ViewLayer.Diffuse Indirect.G",
            "ViewLayer.Diffuse Indirect.B",
            "ViewLayer.Diffuse Color.R",
            "ViewLayer.Diffuse Color.G",
            "ViewLayer.Diffuse Color.B",
        ];
        let mut planes: NamedPlanes =
            names.iter().enumerate().map(|(i, n)| (n.to_string(), vec![i as f32 + 1.0; 2])).collect();
        derive(&mut planes, 2, &ChannelMaps::default());
        let get = |n: &str| planes.iter().find(|(k, _)| k == n).map(|(_, p)| p[0]).unwrap();
        // diffuse.R = (DiffDir.R + DiffInd.R) × DiffCol.R = (5 + 8) × 11
        assert_eq!(get("diffuse.R"), 13.0 * 11.0);
        // specular.R = Combined.R − diffuse.R
        assert_eq!(get("specular.R"), 1.0 - 143.0);
        assert_eq!(get("diffuse.B"), (7.0 + 10.0) * 13.0);
    }

    #[test]
    fn the_beauty_is_rgb_else_cycles_combined() {
        let b = beauty(&["G", "A", "R", "B", "diffuse.R"]);
        assert_eq!((b.color, b.alpha), (vec!["R", "G", "B"], Some("A")));
        let b = beauty(&["VL.Combined.R", "VL.Combined.G", "VL.Combined.B", "VL.Combined.A", "VL.Depth.Z"]);
        assert_eq!(
            (b.color, b.alpha),
            (vec!["VL.Combined.R", "VL.Combined.G", "VL.Combined.B"], Some("VL.Combined.A"))
        );
        assert_eq!(beauty(&["diffuse.R", "R", "G"]), Beauty::default());
    }

    #[test]
    fn recipes_name_their_sources() {
        let r = Recipe::Remainder { total: "t".into(), terms: vec!["a".into(), "b".into()], factor: "f".into() };
        assert_eq!(r.sources(), ["t", "a", "b", "f"]);
        assert!(Recipe::Zero.sources().is_empty());
    }

    #[test]
    fn canonical_files_derive_nothing() {
        let canonical = ["diffuse.R", "diffuse.G", "diffuse.B", "specular.R", "specular.G", "specular.B"];
        assert!(recipes(&canonical, &ChannelMaps::default()).is_empty());
    }
}
