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

//! Renderers' own AOV names: Arnold, RenderMan, V-Ray, Karma and Redshift, and the channel
//! maps an operator adds in the configuration file or a client sends with a job.
//!
//! A frame that holds neither the canonical buffers (docs/frame-layout.md) nor Blender
//! Cycles' passes is tried against each map in turn (the configured ones first, then the
//! shipped presets): the first whose diffuse, albedo, normal and depth AOVs are all in the
//! file maps it. Its specular is the map's own `specular` when it names one, else the
//! beauty minus the diffuse (glossy, transmission, emission and the rest), so that the two
//! components add up to the beauty exactly. Each map lists, per canonical buffer, the AOVs
//! that give it: `a + b` sums layers, `a - b` subtracts one, `|` separates alternatives
//! (the first present wins). Layer names are matched without regard to case, and a layer's
//! channels may be `R,G,B` or `X,Y,Z` in either case; a one-channel buffer (depth) is the
//! layer itself or its single channel. `beauty` is the file's top-level `R,G,B` unless a
//! map names its own (RenderMan's `Ci`, Karma's `C`).
//!
//! A job may name one map (`channel_map=arnold`) or carry its own
//! (`channel_map=diffuse=diff_d+diff_i;albedo=alb;normal=N;depth=Z`); the frame is then read
//! through that map alone, and a missing AOV is named in that map's terms.
//!
//! A frame that matches a map in part is refused with the AOVs that renderer must be told
//! to write ([`ChannelMaps::hint`]).

use std::collections::BTreeMap;
use std::sync::{Arc, OnceLock};

use serde::Deserialize;

use super::layout::Buffer;
use super::renderers::Recipe;

/// One renderer's AOV names: how the canonical buffers are made from its layers.
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelMap {
    /// The map's name, as jobs and the configuration file name it (lower case).
    pub name: String,
    /// The renderer, as messages name it.
    pub renderer: String,
    /// The beauty layer ("" for the top-level `R,G,B`).
    pub beauty: String,
    pub diffuse: String,
    /// The specular expression; `None`: the beauty minus the diffuse.
    pub specular: Option<String>,
    pub albedo: String,
    pub normal: String,
    pub depth: String,
    /// Optional: (canonical buffer, AOVs) for the covariance and the variances.
    pub extra: Vec<(Buffer, String)>,
}

/// A channel map as the configuration file writes it (`[channel_maps.<name>]`), and as a
/// job's inline map is parsed.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ChannelMapSpec {
    /// The renderer's name in messages (default: the map's name).
    pub renderer: Option<String>,
    /// The beauty layer (default: the top-level `R,G,B`).
    pub beauty: Option<String>,
    pub diffuse: Option<String>,
    pub specular: Option<String>,
    pub albedo: Option<String>,
    pub normal: Option<String>,
    pub depth: Option<String>,
    pub covariance: Option<String>,
    /// Canonical variance buffer (`diffuseVariance`, ...) → AOVs.
    #[serde(default)]
    pub variances: BTreeMap<String, String>,
}

/// The keys a map may set, for messages.
const KEYS: &str = "renderer, beauty, diffuse, specular, albedo, normal, depth, covariance, variances";
/// The variance buffers a map may name.
const VARIANCES: [Buffer; 6] = [
    Buffer::DiffuseVariance,
    Buffer::SpecularVariance,
    Buffer::AlbedoVariance,
    Buffer::NormalVariance,
    Buffer::DepthVariance,
    Buffer::CovarianceVariance,
];
/// Longest inline map a job may carry, in bytes.
pub const MAX_INLINE_MAP_BYTES: usize = 2048;

/// Checks one expression: non-empty terms of layer names, joined by `+`, `-` and `|`.
fn check_expression(key: &str, expr: &str) -> Result<(), String> {
    for alt in expr.split('|') {
        for (_, term) in terms(alt) {
            if term.is_empty() {
                return Err(format!("`{key} = \"{expr}\"` has an empty layer name"));
            }
            if term.chars().any(|c| c.is_control() || c == '=' || c == ';') {
                return Err(format!(
                    "`{key} = \"{expr}\"`: layer name `{term}` contains `=`, `;` or a control character"
                ));
            }
        }
    }
    Ok(())
}

/// The signed terms of one alternative: `a + b - c` → (+1, a), (+1, b), (−1, c). A minus
/// needs a space on each side (` - `): layer names may contain `-`.
fn terms(alt: &str) -> Vec<(f32, &str)> {
    let mut out = Vec::new();
    for (i, part) in alt.split(" - ").enumerate() {
        for (j, term) in part.split('+').enumerate() {
            out.push((if i > 0 && j == 0 { -1.0 } else { 1.0 }, term.trim()));
        }
    }
    out
}

impl ChannelMap {
    /// A map from its specification; the message names the key that is wrong.
    pub fn new(name: &str, spec: ChannelMapSpec) -> Result<ChannelMap, String> {
        let name = name.trim().to_ascii_lowercase();
        if name.is_empty() || name == "auto" || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            return Err(format!(
                "channel map name `{name}`: use letters, digits, `_` and `-` (and not `auto`, which means every map in turn)"
            ));
        }
        let required = |key: &str, v: Option<String>| -> Result<String, String> {
            let v = v.filter(|v| !v.trim().is_empty()).ok_or_else(|| {
                format!("channel map `{name}` has no `{key}`: diffuse, albedo, normal and depth are required")
            })?;
            check_expression(key, &v)?;
            Ok(v)
        };
        let diffuse = required("diffuse", spec.diffuse)?;
        let albedo = required("albedo", spec.albedo)?;
        let normal = required("normal", spec.normal)?;
        let depth = required("depth", spec.depth)?;
        let beauty = spec.beauty.unwrap_or_default().trim().to_string();
        if beauty.contains(['+', '-', '|']) {
            return Err(format!("channel map `{name}`: `beauty` is one layer, not an expression"));
        }
        let specular = spec.specular.filter(|s| !s.trim().is_empty());
        if let Some(s) = &specular {
            check_expression("specular", s)?;
        }
        let mut extra = Vec::new();
        if let Some(c) = spec.covariance.filter(|c| !c.trim().is_empty()) {
            check_expression("covariance", &c)?;
            extra.push((Buffer::Covariance, c));
        }
        for (key, expr) in spec.variances {
            let buffer = VARIANCES.iter().copied().find(|b| b.name().eq_ignore_ascii_case(&key)).ok_or_else(|| {
                format!(
                    "channel map `{name}`: unknown variance `{key}` (expected {})",
                    VARIANCES.map(|b| b.name()).join(", ")
                )
            })?;
            check_expression(&key, &expr)?;
            extra.push((buffer, expr));
        }
        Ok(ChannelMap {
            renderer: spec.renderer.unwrap_or_else(|| name.clone()),
            name,
            beauty,
            diffuse,
            specular,
            albedo,
            normal,
            depth,
            extra,
        })
    }

    /// A job's inline map: `key=expr` pairs separated by `;` (`variances.diffuseVariance=...`
    /// for variances).
    fn inline(text: &str) -> Result<ChannelMap, String> {
        let mut spec = ChannelMapSpec::default();
        for pair in text.split(';').map(str::trim).filter(|p| !p.is_empty()) {
            let (key, value) = pair
                .split_once('=')
                .ok_or_else(|| format!("channel_map: `{pair}` is not `key=AOVs` (keys: {KEYS})"))?;
            let (key, value) = (key.trim(), Some(value.trim().to_string()));
            match key {
                "renderer" => spec.renderer = value,
                "beauty" => spec.beauty = value,
                "diffuse" => spec.diffuse = value,
                "specular" => spec.specular = value,
                "albedo" => spec.albedo = value,
                "normal" => spec.normal = value,
                "depth" => spec.depth = value,
                "covariance" => spec.covariance = value,
                _ => match key.strip_prefix("variances.") {
                    Some(v) => {
                        spec.variances.insert(v.to_string(), value.unwrap_or_default());
                    }
                    None => return Err(format!("channel_map: unknown key `{key}` (expected {KEYS})")),
                },
            }
        }
        ChannelMap::new("job", spec)
    }

    fn shipped(
        name: &str,
        renderer: &str,
        beauty: &str,
        [diffuse, albedo, normal, depth]: [&str; 4],
        variances: &[(&str, &str)],
    ) -> ChannelMap {
        let spec = ChannelMapSpec {
            renderer: Some(renderer.into()),
            beauty: Some(beauty.into()),
            diffuse: Some(diffuse.into()),
            albedo: Some(albedo.into()),
            normal: Some(normal.into()),
            depth: Some(depth.into()),
            variances: variances.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect(),
            ..Default::default()
        };
        ChannelMap::new(name, spec).expect("the shipped presets are valid")
    }

    /// The map's required expressions, by key.
    fn required(&self) -> [(&'static str, &str); 4] {
        [("diffuse", &self.diffuse), ("albedo", &self.albedo), ("normal", &self.normal), ("depth", &self.depth)]
    }
}

/// The shipped presets, in the order they are tried. The docs/frame-layout.md table
/// repeats them.
fn shipped() -> Vec<ChannelMap> {
    vec![
        ChannelMap::shipped(
            "arnold",
            "Arnold",
            "",
            ["diffuse_direct + diffuse_indirect | diffuse", "denoise_albedo | albedo | diffuse_albedo", "N", "Z"],
            &[],
        ),
        ChannelMap::shipped(
            "renderman",
            "RenderMan",
            "Ci",
            ["diffuse", "albedo", "normal", "zfiltered"],
            &[
                ("diffuseVariance", "diffuse_mse"),
                ("specularVariance", "specular_mse"),
                ("albedoVariance", "albedo_var"),
                ("normalVariance", "normal_var"),
                ("depthVariance", "zfiltered_var"),
            ],
        ),
        ChannelMap::shipped(
            "karma",
            "Karma",
            "C",
            ["diffuse | directdiffuse + indirectdiffuse", "albedo", "N", "depth | Pz"],
            &[],
        ),
        ChannelMap::shipped(
            "vray",
            "V-Ray",
            "",
            ["Lighting + GI", "DiffuseFilter", "BumpNormals | Normals", "ZDepth"],
            &[],
        ),
        ChannelMap::shipped(
            "redshift",
            "Redshift",
            "",
            ["DiffuseLighting + GI", "DiffuseFilter", "N | Normals", "Z | Depth"],
            &[],
        ),
    ]
}

/// The channel maps a frame is read with: every map tried in turn (the daemon's), or the
/// one a job named or carried.
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelMaps {
    maps: Arc<Vec<ChannelMap>>,
    /// One map chosen by the job: Cycles' passes are not looked for, and a missing AOV is
    /// named in this map's terms.
    chosen: bool,
}

impl Default for ChannelMaps {
    /// The shipped presets.
    fn default() -> ChannelMaps {
        static SHIPPED: OnceLock<Arc<Vec<ChannelMap>>> = OnceLock::new();
        ChannelMaps { maps: SHIPPED.get_or_init(|| Arc::new(shipped())).clone(), chosen: false }
    }
}

impl ChannelMaps {
    /// The configured maps, tried before the shipped presets; one named like a preset
    /// replaces it.
    pub fn configured(configured: Vec<ChannelMap>) -> ChannelMaps {
        let mut maps = configured;
        let replaced: Vec<String> = maps.iter().map(|m| m.name.clone()).collect();
        maps.extend(shipped().into_iter().filter(|p| !replaced.contains(&p.name)));
        ChannelMaps { maps: Arc::new(maps), chosen: false }
    }

    /// The maps, in the order they are tried.
    pub fn iter(&self) -> impl Iterator<Item = &ChannelMap> {
        self.maps.iter()
    }

    /// The maps' names, in the order they are tried.
    pub fn names(&self) -> Vec<&str> {
        self.maps.iter().map(|m| m.name.as_str()).collect()
    }

    /// The maps a job reads its frame with: `""` or `auto`, every map; a name, that map
    /// alone; `key=AOVs;...`, the job's own map.
    /// A choice longer than [`MAX_INLINE_MAP_BYTES`] is refused, whatever it is.
    pub fn choose(&self, choice: &str) -> Result<ChannelMaps, String> {
        if choice.len() > MAX_INLINE_MAP_BYTES {
            return Err(format!("channel_map is {} bytes, at most {MAX_INLINE_MAP_BYTES} are accepted", choice.len()));
        }
        let choice = choice.trim();
        if choice.is_empty() || choice.eq_ignore_ascii_case("auto") {
            return Ok(self.clone());
        }
        let map = if choice.contains(['=', ';']) {
            ChannelMap::inline(choice)?
        } else {
            self.maps.iter().find(|m| m.name.eq_ignore_ascii_case(choice)).cloned().ok_or_else(|| {
                format!(
                    "unknown channel map `{choice}` (expected auto, {}, or key=AOVs pairs)",
                    self.names().join(", ")
                )
            })?
        };
        Ok(ChannelMaps { maps: Arc::new(vec![map]), chosen: true })
    }

    /// Whether the job chose one map (Cycles' passes are then not looked for).
    pub fn chosen(&self) -> bool {
        self.chosen
    }

    /// The first map that maps `names` completely: its renderer and recipes.
    pub fn recipes(&self, names: &[&str]) -> Option<(&str, Vec<(String, Recipe)>)> {
        self.maps.iter().find_map(|p| recipes_of(p, names).map(|r| (p.renderer.as_str(), r)))
    }

    /// For a frame that no map maps: the map the job chose, else the renderer whose AOVs it
    /// has most of (at least two of its diffuse, albedo, normal and depth layers), and what
    /// that renderer must write.
    pub fn hint(&self, names: &[&str]) -> Option<String> {
        let present = |expr: &str| {
            expr.split('|').any(|alt| {
                terms(alt).iter().all(|(_, l)| channels(names, l, 3).is_some() || channels(names, l, 1).is_some())
            })
        };
        let score = |p: &ChannelMap| p.required().iter().filter(|(_, expr)| present(expr)).count();
        let best = if self.chosen {
            self.maps.first()?
        } else {
            self.maps.iter().max_by_key(|p| score(p)).filter(|p| score(p) >= 2)?
        };
        let beauty = if best.beauty.is_empty() { "the beauty R,G,B".to_string() } else { best.beauty.clone() };
        let beauty_missing = channels(names, &best.beauty, 3).is_none();
        let missing: Vec<String> = best
            .required()
            .iter()
            .filter(|(_, expr)| !present(expr))
            .map(|(key, expr)| format!("{key}: {expr}"))
            .chain(beauty_missing.then(|| format!("beauty: {beauty}")))
            .collect();
        let lead = if self.chosen {
            format!("the job reads the frame through channel map `{}` ({})", best.name, best.renderer)
        } else {
            format!("this looks like {} output", best.renderer)
        };
        Some(format!(
            "{lead}: write the AOVs it lacks ({}); it reads diffuse from {}, albedo from {}, normal from {}, depth from {} \
             (see docs/frame-layout.md)",
            missing.join("; "),
            best.diffuse,
            best.albedo,
            best.normal,
            best.depth
        ))
    }
}

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
        for (sign, term) in terms(alt) {
            for (c, ch) in channels(names, term, count)?.into_iter().enumerate() {
                sums[c].push((sign, ch));
            }
        }
        Some(sums)
    })
}

/// How `map` derives the canonical channels from `names`, or `None` when a required AOV
/// is missing.
fn recipes_of(map: &ChannelMap, names: &[&str]) -> Option<Vec<(String, Recipe)>> {
    let rgb = ["R", "G", "B"];
    let diffuse = resolve(names, &map.diffuse, 3)?;
    let specular = match &map.specular {
        Some(expr) => resolve(names, expr, 3)?,
        None => {
            let beauty = channels(names, &map.beauty, 3)?;
            diffuse
                .iter()
                .zip(beauty)
                .map(|(d, total)| std::iter::once((1.0, total)).chain(d.iter().map(|(s, n)| (-s, n.clone()))).collect())
                .collect()
        }
    };
    let mut out = Vec::new();
    let mut add = |buffer: &str, sums: Vec<Vec<(f32, String)>>| {
        let suffixes: &[&str] = if sums.len() == 1 { &["Z"] } else { &rgb };
        for (s, sum) in suffixes.iter().zip(sums) {
            out.push((format!("{buffer}.{s}"), Recipe::Signed(sum)));
        }
    };
    add("diffuse", diffuse);
    add("specular", specular);
    for (buffer, expr, count) in [("albedo", &map.albedo, 3), ("normal", &map.normal, 3), ("depth", &map.depth, 1)] {
        add(buffer, resolve(names, expr, count)?);
    }
    for (buffer, expr) in &map.extra {
        let counts: &[usize] = if *buffer == Buffer::Covariance { &[1] } else { &[3, 1] };
        if let Some(sums) = counts.iter().find_map(|&count| resolve(names, expr, count)) {
            add(buffer.name(), sums);
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn signed(terms: &[(f32, &str)]) -> Recipe {
        Recipe::Signed(terms.iter().map(|(s, n)| (*s, n.to_string())).collect())
    }

    #[test]
    fn arnold_names_map_with_the_specular_as_the_remainder() {
        let names = [
            "R",
            "G",
            "B",
            "A",
            "diffuse_direct.R",
            "diffuse_direct.G",
            "diffuse_direct.B",
            "diffuse_indirect.R",
            "diffuse_indirect.G",
            "diffuse_indirect.B",
            "denoise_albedo.R",
            "denoise_albedo.G",
            "denoise_albedo.B",
            "N.X",
            "N.Y",
            "N.Z",
            "Z",
        ];
        let maps = ChannelMaps::default();
        let (renderer, recipes) = maps.recipes(&names).unwrap();
        assert_eq!(renderer, "Arnold");
        let get = |n: &str| recipes.iter().find(|(k, _)| k == n).map(|(_, r)| r.clone()).unwrap();
        assert_eq!(get("specular.G"), signed(&[(1.0, "G"), (-1.0, "diffuse_direct.G"), (-1.0, "diffuse_indirect.G")]));
        assert_eq!(get("normal.B"), signed(&[(1.0, "N.Z")]));
        assert_eq!(get("depth.Z"), signed(&[(1.0, "Z")]));
    }

    #[test]
    fn names_match_without_case_and_a_partial_match_is_a_hint() {
        let maps = ChannelMaps::default();
        let names = ["Ci.r", "Ci.g", "Ci.b", "diffuse.r", "diffuse.g", "diffuse.b", "normal.r", "normal.g", "normal.b"];
        assert!(maps.recipes(&names).is_none());
        let said = maps.hint(&names).unwrap();
        assert!(
            said.contains("RenderMan") && said.contains("depth: zfiltered") && !said.contains("normal: normal"),
            "{said}"
        );
        let mut all = names.to_vec();
        all.extend([
            "albedo.r",
            "albedo.g",
            "albedo.b",
            "zfiltered.r",
            "diffuse_mse.r",
            "diffuse_mse.g",
            "diffuse_mse.b",
        ]);
        let (renderer, recipes) = maps.recipes(&all).unwrap();
        assert_eq!(renderer, "RenderMan");
        assert!(recipes.iter().any(|(n, _)| n == "diffuseVariance.G"));
        assert!(maps.hint(&["R", "G", "B"]).is_none());
    }

    #[test]
    fn a_configured_map_is_tried_first_and_may_name_its_specular() {
        let spec: ChannelMapSpec = toml::from_str(
            r#"
            renderer = "Studio"
            diffuse = "diff_d + diff_i"
            specular = "spec-total - emit"
            albedo = "alb"
            normal = "nrm"
            depth = "z"
            variances = { diffuseVariance = "diff_var" }
            "#,
        )
        .unwrap();
        let maps = ChannelMaps::configured(vec![ChannelMap::new("studio", spec).unwrap()]);
        assert_eq!(maps.names(), ["studio", "arnold", "renderman", "karma", "vray", "redshift"]);
        let mut names = Vec::new();
        for layer in ["diff_d", "diff_i", "spec-total", "emit", "alb", "nrm", "diff_var"] {
            names.extend(["R", "G", "B"].map(|c| format!("{layer}.{c}")));
        }
        names.push("z".into());
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        let (renderer, recipes) = maps.recipes(&names).unwrap();
        assert_eq!(renderer, "Studio");
        let get = |n: &str| recipes.iter().find(|(k, _)| k == n).map(|(_, r)| r.clone()).unwrap();
        // A layer named with `-` is one layer; ` - ` subtracts.
        assert_eq!(get("specular.B"), signed(&[(1.0, "spec-total.B"), (-1.0, "emit.B")]));
        assert_eq!(get("diffuseVariance.R"), signed(&[(1.0, "diff_var.R")]));
        assert_eq!(get("depth.Z"), signed(&[(1.0, "z")]));
    }

    #[test]
    fn a_job_chooses_one_map_by_name_or_inline_and_is_told_what_it_lacks() {
        let maps = ChannelMaps::default();
        let arnold = maps.choose("Arnold").unwrap();
        assert!(arnold.chosen() && arnold.names() == ["arnold"]);
        assert_eq!(maps.choose("auto").unwrap(), maps);
        let err = maps.choose("maya").unwrap_err();
        assert!(err.contains("unknown channel map `maya`") && err.contains("arnold, renderman"), "{err}");

        // Arnold output without its depth AOV, read through the Arnold map: named in its terms.
        let names = [
            "R",
            "G",
            "B",
            "diffuse.R",
            "diffuse.G",
            "diffuse.B",
            "albedo.R",
            "albedo.G",
            "albedo.B",
            "N.X",
            "N.Y",
            "N.Z",
        ];
        let said = arnold.hint(&names).unwrap();
        assert!(said.contains("channel map `arnold` (Arnold)") && said.contains("(depth: Z)"), "{said}");

        let inline = maps.choose("diffuse=d1 + d2; albedo=a; normal=n; depth=z; variances.diffuseVariance=dv").unwrap();
        let names = [
            "R", "G", "B", "d1.R", "d1.G", "d1.B", "d2.R", "d2.G", "d2.B", "a.R", "a.G", "a.B", "n.X", "n.Y", "n.Z",
            "z.Z", "dv.Y",
        ];
        let (renderer, recipes) = inline.recipes(&names).unwrap();
        assert_eq!(renderer, "job");
        assert!(recipes.iter().any(|(n, r)| n == "diffuseVariance.Z" && *r == signed(&[(1.0, "dv.Y")])));
    }

    #[test]
    fn bad_maps_are_refused_naming_the_key() {
        let maps = ChannelMaps::default();
        for (text, says) in [
            ("diffuse=d;albedo=a;normal=n", "has no `depth`"),
            ("diffuse=d;albedo=a;normal=n;depth=z;colour=c", "unknown key `colour`"),
            ("diffuse=d + ;albedo=a;normal=n;depth=z", "empty layer name"),
            ("diffuse=d;albedo=a;normal=n;depth=z;variances.depthVar=v", "unknown variance `depthVar`"),
            ("diffuse=d;albedo=a;normal=n;depth=z;beauty=a+b", "`beauty` is one layer"),
            ("diffuse", "is not `key=AOVs`"),
        ] {
            let err = maps.choose(&format!("{text};")).unwrap_err();
            assert!(err.contains(says), "{text}: {err}");
        }
        assert!(maps.choose(&format!("diffuse={}", "x".repeat(MAX_INLINE_MAP_BYTES))).unwrap_err().contains("at most"));
        let err = ChannelMap::new("auto", ChannelMapSpec::default()).unwrap_err();
        assert!(err.contains("not `auto`"), "{err}");
    }
}
