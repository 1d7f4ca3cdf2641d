//! Renderers' own AOV names: Arnold, RenderMan, V-Ray, Karma and Redshift.
//!
//! A frame that holds neither the canonical buffers (docs/frame-layout.md) nor Blender
//! Cycles' passes is tried against each renderer's preset in turn: the first whose
//! diffuse, albedo, normal and depth AOVs are all in the file maps it, and its specular is
//! the beauty minus the diffuse (glossy, transmission, emission and the rest), so that the
//! two components add up to the beauty exactly. Each preset lists, per canonical buffer,
//! the AOVs that give it: `a + b` sums layers, `|` separates alternatives (the first present
//! wins). Layer names are matched without regard to case, and a layer's channels may be
//! `R,G,B` or `X,Y,Z` in either case; a one-channel buffer (depth) is the layer itself or
//! its single channel. `beauty` is the file's top-level `R,G,B` unless a preset names its
//! own (RenderMan's `Ci`, Karma's `C`).
//!
//! A frame that matches a preset in part is refused with the AOVs that renderer must be
//! told to write ([`hint`]).

use super::renderers::Recipe;

/// One renderer's AOV names.
pub struct Preset {
    /// The renderer, as messages name it.
    pub renderer: &'static str,
    /// The beauty layer ("" for the top-level `R,G,B`).
    pub beauty: &'static str,
    pub diffuse: &'static str,
    pub albedo: &'static str,
    pub normal: &'static str,
    pub depth: &'static str,
    /// Optional variances: (canonical variance buffer, AOVs).
    pub variances: &'static [(&'static str, &'static str)],
}

/// The presets, in the order they are tried. The docs/frame-layout.md table repeats them.
pub const PRESETS: &[Preset] = &[
    Preset {
        renderer: "Arnold",
        beauty: "",
        diffuse: "diffuse_direct + diffuse_indirect | diffuse",
        albedo: "denoise_albedo | albedo | diffuse_albedo",
        normal: "N",
        depth: "Z",
        variances: &[],
    },
    Preset {
        renderer: "RenderMan",
        beauty: "Ci",
        diffuse: "diffuse",
        albedo: "albedo",
        normal: "normal",
        depth: "zfiltered",
        variances: &[
            ("diffuseVariance", "diffuse_mse"),
            ("specularVariance", "specular_mse"),
            ("albedoVariance", "albedo_var"),
            ("normalVariance", "normal_var"),
            ("depthVariance", "zfiltered_var"),
        ],
    },
    Preset {
        renderer: "Karma",
        beauty: "C",
        diffuse: "diffuse | directdiffuse + indirectdiffuse",
        albedo: "albedo",
        normal: "N",
        depth: "depth | Pz",
        variances: &[],
    },
    Preset {
        renderer: "V-Ray",
        beauty: "",
        diffuse: "Lighting + GI",
        albedo: "DiffuseFilter",
        normal: "BumpNormals | Normals",
        depth: "ZDepth",
        variances: &[],
    },
    Preset {
        renderer: "Redshift",
        beauty: "",
        diffuse: "DiffuseLighting + GI",
        albedo: "DiffuseFilter",
        normal: "N | Normals",
        depth: "Z | Depth",
        variances: &[],
    },
];

/// The channels of `layer` with 3 (`R,G,B` or `X,Y,Z`) or 1 component(s), as file names.
fn channels(names: &[&str], layer: &str, count: usize) -> Option<Vec<String>> {
    let find = |full: &str| names.iter().find(|n| n.eq_ignore_ascii_case(full)).map(|n| n.to_string());
    if count == 1 {
        let one = find(layer).or_else(|| ["Z", "Y", "V", "R"].iter().find_map(|c| find(&format!("{layer}.{c}"))));
        return one.map(|n| vec![n]);
    }
    let prefix = if layer.is_empty() { String::new() } else { format!("{layer}.") };
    [["R", "G", "B"], ["X", "Y", "Z"]]
        .iter()
        .find_map(|set| set.iter().map(|c| find(&format!("{prefix}{c}"))).collect::<Option<Vec<_>>>())
}

/// An expression's first alternative whose layers are all present, as per-component sums
/// of `(sign, channel)`.
fn resolve(names: &[&str], expr: &str, count: usize) -> Option<Vec<Vec<(f32, String)>>> {
    expr.split('|').find_map(|alt| {
        let mut sums = vec![Vec::new(); count];
        for term in alt.split('+') {
            for (c, ch) in channels(names, term.trim(), count)?.into_iter().enumerate() {
                sums[c].push((1.0, ch));
            }
        }
        Some(sums)
    })
}

/// The layer names of an expression, for messages.
fn layers(expr: &str) -> impl Iterator<Item = &str> {
    expr.split(['|', '+']).map(str::trim)
}

/// How `preset` derives the canonical channels from `names`, or `None` when a required
/// AOV is missing.
fn recipes_of(preset: &Preset, names: &[&str]) -> Option<Vec<(String, Recipe)>> {
    let beauty = channels(names, preset.beauty, 3)?;
    let diffuse = resolve(names, preset.diffuse, 3)?;
    let mut out = Vec::new();
    for (c, (d, total)) in ["R", "G", "B"].iter().zip(diffuse.iter().zip(&beauty)) {
        out.push((format!("diffuse.{c}"), Recipe::Signed(d.clone())));
        let mut rest = vec![(1.0, total.clone())];
        rest.extend(d.iter().map(|(s, n)| (-s, n.clone())));
        out.push((format!("specular.{c}"), Recipe::Signed(rest)));
    }
    for (buffer, expr, count) in
        [("albedo", preset.albedo, 3), ("normal", preset.normal, 3), ("depth", preset.depth, 1)]
    {
        let sums = resolve(names, expr, count)?;
        let suffixes: &[&str] = if count == 1 { &["Z"] } else { &["R", "G", "B"] };
        for (s, sum) in suffixes.iter().zip(sums) {
            out.push((format!("{buffer}.{s}"), Recipe::Signed(sum)));
        }
    }
    for (buffer, expr) in preset.variances {
        for count in [3, 1] {
            if let Some(sums) = resolve(names, expr, count) {
                let suffixes: &[&str] = if count == 1 { &["Z"] } else { &["R", "G", "B"] };
                for (s, sum) in suffixes.iter().zip(sums) {
                    out.push((format!("{buffer}.{s}"), Recipe::Signed(sum)));
                }
                break;
            }
        }
    }
    Some(out)
}

/// The first preset that maps `names` completely: its renderer and recipes.
pub fn recipes(names: &[&str]) -> Option<(&'static str, Vec<(String, Recipe)>)> {
    PRESETS.iter().find_map(|p| recipes_of(p, names).map(|r| (p.renderer, r)))
}

/// For a frame that no preset maps: the renderer whose AOVs it has most of (at least two
/// of its diffuse, albedo, normal and depth layers), and what that renderer must write.
pub fn hint(names: &[&str]) -> Option<String> {
    let score = |p: &Preset| {
        [p.diffuse, p.albedo, p.normal, p.depth]
            .iter()
            .filter(|expr| layers(expr).any(|l| channels(names, l, 3).is_some() || channels(names, l, 1).is_some()))
            .count()
    };
    let best = PRESETS.iter().max_by_key(|p| score(p)).filter(|p| score(p) >= 2)?;
    let beauty = if best.beauty.is_empty() { "the beauty R,G,B" } else { best.beauty };
    Some(format!(
        "this looks like {} output: write the AOVs {} (diffuse: {}; albedo: {}; normal: {}; depth: {}), \
         see docs/frame-layout.md",
        best.renderer, beauty, best.diffuse, best.albedo, best.normal, best.depth
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arnold_names_map_with_the_specular_as_the_remainder() {
        let names = [
            "R", "G", "B", "A", "diffuse_direct.R", "diffuse_direct.G", "diffuse_direct.B", "diffuse_indirect.R",
            "diffuse_indirect.G", "diffuse_indirect.B", "denoise_albedo.R", "denoise_albedo.G", "denoise_albedo.B",
            "N.X", "N.Y", "N.Z", "Z",
        ];
        let (renderer, recipes) = recipes(&names).unwrap();
        assert_eq!(renderer, "Arnold");
        let get = |n: &str| recipes.iter().find(|(k, _)| k == n).map(|(_, r)| r.clone()).unwrap();
        assert_eq!(
            get("specular.G"),
            Recipe::Signed(vec![(1.0, "G".into()), (-1.0, "diffuse_direct.G".into()), (-1.0, "diffuse_indirect.G".into())])
        );
        assert_eq!(get("normal.B"), Recipe::Signed(vec![(1.0, "N.Z".into())]));
        assert_eq!(get("depth.Z"), Recipe::Signed(vec![(1.0, "Z".into())]));
    }

    #[test]
    fn names_match_without_case_and_a_partial_match_is_a_hint() {
        let names = ["Ci.r", "Ci.g", "Ci.b", "diffuse.r", "diffuse.g", "diffuse.b", "normal.r", "normal.g", "normal.b"];
        assert!(recipes(&names).is_none());
        let said = hint(&names).unwrap();
        assert!(said.contains("RenderMan") && said.contains("zfiltered"), "{said}");
        let mut all = names.to_vec();
        all.extend(["albedo.r", "albedo.g", "albedo.b", "zfiltered.r", "diffuse_mse.r", "diffuse_mse.g", "diffuse_mse.b"]);
        let (renderer, recipes) = recipes(&all).unwrap();
        assert_eq!(renderer, "RenderMan");
        assert!(recipes.iter().any(|(n, _)| n == "diffuseVariance.G"));
        assert!(hint(&["R", "G", "B"]).is_none());
    }
}
