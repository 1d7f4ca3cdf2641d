//! Model contracts v1 and v2: what a model file must declare for the engine to use it.
//! The full text is `docs/model-contract.md`; `training/mcdenoise_train/contract.py` mirrors
//! these constants on the training side.

use std::fmt;

/// Contract v1: one graph per component, one 21×21 kernel (`diffuse.onnx`, `specular.onnx`).
pub const CONTRACT_VERSION: &str = "1";
/// Contract v2: one graph for both components, kernels at several scales (`model.onnx`).
pub const CONTRACT_V2: &str = "2";
/// Side of the predicted kernel (contract v1).
pub const KERNEL_SIZE: usize = 21;
/// Taps per kernel.
pub const TAPS: usize = KERNEL_SIZE * KERNEL_SIZE;
/// Largest tap offset.
pub const KERNEL_RADIUS: usize = KERNEL_SIZE / 2;
/// Channels of the `color` input.
pub const COLOR_CHANNELS: usize = 10;

/// Features of the `full` variant, in input order.
pub const FEATURES_FULL: [&str; 28] = [
    "normal.R",
    "normal.G",
    "normal.B",
    "albedo.R",
    "albedo.G",
    "albedo.B",
    "depth",
    "covariance",
    "normalVariance",
    "albedoVariance",
    "depthVariance",
    "covarianceVariance",
    "gx.normal.R",
    "gx.normal.G",
    "gx.normal.B",
    "gx.albedo.R",
    "gx.albedo.G",
    "gx.albedo.B",
    "gx.depth",
    "gx.covariance",
    "gy.normal.R",
    "gy.normal.G",
    "gy.normal.B",
    "gy.albedo.R",
    "gy.albedo.G",
    "gy.albedo.B",
    "gy.depth",
    "gy.covariance",
];

/// Features of the `nocov` variant, in input order.
pub const FEATURES_NOCOV: [&str; 24] = [
    "normal.R",
    "normal.G",
    "normal.B",
    "albedo.R",
    "albedo.G",
    "albedo.B",
    "depth",
    "normalVariance",
    "albedoVariance",
    "depthVariance",
    "gx.normal.R",
    "gx.normal.G",
    "gx.normal.B",
    "gx.albedo.R",
    "gx.albedo.G",
    "gx.albedo.B",
    "gx.depth",
    "gy.normal.R",
    "gy.normal.G",
    "gy.normal.B",
    "gy.albedo.R",
    "gy.albedo.G",
    "gy.albedo.B",
    "gy.depth",
];

/// Metadata keys (ONNX `metadata_props`).
pub mod keys {
    pub const CONTRACT: &str = "mcdenoise.contract";
    pub const COMPONENT: &str = "mcdenoise.component";
    pub const VARIANT: &str = "mcdenoise.variant";
    pub const KERNEL_SIZE: &str = "mcdenoise.kernel_size";
    pub const FEATURES: &str = "mcdenoise.features";
    pub const RECEPTIVE_RADIUS: &str = "mcdenoise.receptive_radius";
    pub const FLOPS_PER_PIXEL: &str = "mcdenoise.flops_per_pixel";
    pub const ARCHITECTURE: &str = "mcdenoise.architecture";
    /// Contract v2: pyramid levels.
    pub const LEVELS: &str = "mcdenoise.levels";
    /// Contract v2: what region sides must be a multiple of (2^(levels − 1)).
    pub const SIZE_MULTIPLE: &str = "mcdenoise.size_multiple";
    /// Contract v2, optional: who compresses the inputs with symlog, `graph` (absent) or
    /// `engine` ([`super::InputCompression`]).
    pub const INPUT_COMPRESSION: &str = "mcdenoise.input_compression";
    /// Contract v2, optional: what the graph outputs, `kernels` (absent) or `filtered`
    /// ([`super::Outputs`]).
    pub const OUTPUTS: &str = "mcdenoise.outputs";
    /// Contract v2, optional: what the network computes in, `fp32` (absent) or `fp16`
    /// ([`super::Precision`]).
    pub const PRECISION: &str = "mcdenoise.precision";
    /// Contract v2, optional: how the reconstruction's specular pyramid averages, `log`
    /// (absent) or `linear` ([`super::SpecularPyramid`]).
    pub const SPECULAR_PYRAMID: &str = "mcdenoise.specular_pyramid";
    /// Of a stage file (`front`, `middle` or `back`; engine::stages).
    pub const STAGE: &str = "mcdenoise.stage";
    /// Of a stage file: the SHA-256 (hex) of the `model.onnx` it was cut from.
    pub const STAGE_OF: &str = "mcdenoise.stage_of";
}

/// What a contract-v2 graph outputs (docs/model-contract.md, "Reconstruction in the graph").
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Outputs {
    /// Kernel and blend logits per level; the engine reconstructs (`model.onnx`).
    Kernels,
    /// The filtered preprocessed color of each component: the reconstruction is in the
    /// graph (`model-recon.onnx`, for GPUs).
    Filtered,
}

impl Outputs {
    /// The metadata value.
    pub fn name(self) -> &'static str {
        match self {
            Outputs::Kernels => "kernels",
            Outputs::Filtered => "filtered",
        }
    }

    /// The value of [`keys::OUTPUTS`] (absent = `Kernels`).
    pub fn parse(value: Option<&str>) -> Option<Outputs> {
        match value {
            None | Some("kernels") => Some(Outputs::Kernels),
            Some("filtered") => Some(Outputs::Filtered),
            Some(_) => None,
        }
    }
}

/// Where contract-v2 kernels are applied (`--reconstruction`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Reconstruction {
    /// In the graph (`model-recon.onnx`) on a GPU where the variant has one, else in the
    /// engine.
    #[default]
    Auto,
    /// In the engine's own code (`model.onnx`), wherever the networks run.
    Engine,
    /// In the graph: every contract-v2 variant must have `model-recon.onnx`.
    Graph,
}

impl std::str::FromStr for Reconstruction {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Reconstruction::Auto),
            "engine" => Ok(Reconstruction::Engine),
            "graph" => Ok(Reconstruction::Graph),
            other => Err(format!("unknown reconstruction `{other}` (expected `auto`, `engine` or `graph`)")),
        }
    }
}

impl fmt::Display for Reconstruction {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Reconstruction::Auto => "auto",
            Reconstruction::Engine => "engine",
            Reconstruction::Graph => "graph",
        })
    }
}

/// The precision a contract-v2 network computes in, and which file of a variant with the
/// reconstruction in the graph is loaded (docs/model-contract.md, "Half precision").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// `fp16` on a GPU where the variant has `model-recon-fp16.onnx`, else `fp32`.
    #[default]
    Auto,
    /// Float32 throughout.
    Fp32,
    /// The network in float16 (`model-recon-fp16.onnx`, the reconstruction in its graph);
    /// every contract-v2 variant must then have the file.
    Fp16,
    /// A file's precision only: quantised to int8 (`mcdenoise_train.quantize`), loaded like
    /// a float32 one from its own models directory.
    Int8,
}

impl Precision {
    /// The value of [`keys::PRECISION`]: its first word, `fp32` (or absent), `fp16` or
    /// `int8`, may be followed by a description. `Auto` is no file's precision.
    pub fn parse(value: Option<&str>) -> Option<Precision> {
        match value.map(|v| v.split_whitespace().next().unwrap_or("")) {
            None | Some("fp32") => Some(Precision::Fp32),
            Some("fp16") => Some(Precision::Fp16),
            Some("int8") => Some(Precision::Int8),
            Some(_) => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Precision::Auto => "auto",
            Precision::Fp32 => "fp32",
            Precision::Fp16 => "fp16",
            Precision::Int8 => "int8",
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Precision::Auto),
            "fp32" => Ok(Precision::Fp32),
            "fp16" => Ok(Precision::Fp16),
            other => Err(format!("unknown precision `{other}` (expected `auto`, `fp32` or `fp16`)")),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Who applies symlog(x) = sign(x)·ln(1 + |x|) to a contract-v2 graph's inputs
/// (docs/model-contract.md, "Input compression").
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum InputCompression {
    /// The graph itself (contract v1, and v2 models without the key).
    Graph,
    /// The engine, before inference: the graph takes compressed inputs.
    Engine,
}

impl InputCompression {
    /// The value of [`keys::INPUT_COMPRESSION`] (absent = `Graph`).
    pub fn parse(value: Option<&str>) -> Option<InputCompression> {
        match value {
            None | Some("graph") => Some(InputCompression::Graph),
            Some("engine") => Some(InputCompression::Engine),
            Some(_) => None,
        }
    }
}

/// How a contract-v2 reconstruction builds the specular's pyramid (docs/model-contract.md,
/// "Reconstruction"): the specular color is ln(1 + s), and its coarser levels are the 2×2
/// means of that (`Log`, v2 models without the key) or ln(1 + the 2×2 means of s) (`Linear`).
/// The diffuse's levels are always the means of its color.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SpecularPyramid {
    Log,
    Linear,
}

impl SpecularPyramid {
    /// The value of [`keys::SPECULAR_PYRAMID`] (absent = `Log`).
    pub fn parse(value: Option<&str>) -> Option<SpecularPyramid> {
        match value {
            None | Some("log") => Some(SpecularPyramid::Log),
            Some("linear") => Some(SpecularPyramid::Linear),
            Some(_) => None,
        }
    }
}

/// A model variant: the name of its directory under the models directory (`full`, `nocov`,
/// `lin2020`, ...), which its `mcdenoise.variant` metadata repeats.
///
/// At most [`Variant::MAX_LEN`] bytes of ASCII letters, digits, `_`, `-` and `.`, starting
/// with a letter or digit; held inline so that the type stays `Copy`. Which inputs a variant
/// takes is not part of its name: it is the loaded model's [`FeatureSet`].
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Variant {
    len: u8,
    bytes: [u8; Variant::MAX_LEN],
}

impl Variant {
    /// Longest variant name, in bytes.
    pub const MAX_LEN: usize = 31;
    /// The variant the engine picks for frames with covariance.
    #[allow(non_upper_case_globals)]
    pub const Full: Variant = Variant::from_static("full");
    /// The variant the engine picks for frames without covariance.
    #[allow(non_upper_case_globals)]
    pub const Nocov: Variant = Variant::from_static("nocov");
    /// The variant for frames without the diffuse/specular split (a beauty with albedo and
    /// normal): a `nocov`-contract model fed the beauty in the diffuse slot, the specular
    /// zero, no variances ([`crate::frame::Frame::to_beauty`]).
    #[allow(non_upper_case_globals)]
    pub const Beauty: Variant = Variant::from_static("beauty");

    const fn from_static(name: &str) -> Variant {
        let src = name.as_bytes();
        let mut bytes = [0u8; Variant::MAX_LEN];
        let mut i = 0;
        while i < src.len() {
            bytes[i] = src[i];
            i += 1;
        }
        Variant { len: src.len() as u8, bytes }
    }

    pub fn name(&self) -> &str {
        // Only `parse` and `from_static` build a Variant, both from ASCII.
        std::str::from_utf8(&self.bytes[..self.len as usize]).expect("variant names are ASCII")
    }

    /// The variant called `name`, if `name` is a valid variant name (whether such a variant
    /// is loaded is the engine's question).
    pub fn parse(name: &str) -> Option<Variant> {
        let ok = |b: u8| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-' | b'.');
        let b = name.as_bytes();
        (!b.is_empty() && b.len() <= Variant::MAX_LEN && b[0].is_ascii_alphanumeric() && b.iter().all(|&c| ok(c)))
            .then(|| Variant::from_static(name))
    }

    /// A variant choice where `auto` (or nothing) lets the frame decide: `None`.
    pub fn parse_choice(s: &str) -> Result<Option<Variant>, String> {
        match s {
            "" | "auto" => Ok(None),
            other => other.parse().map(Some),
        }
    }
}

impl fmt::Display for Variant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl fmt::Debug for Variant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Variant({})", self.name())
    }
}

impl serde::Serialize for Variant {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> serde::Deserialize<'de> for Variant {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Variant, D::Error> {
        let name = <std::borrow::Cow<'de, str>>::deserialize(d)?;
        Variant::parse(&name).ok_or_else(|| serde::de::Error::custom(format!("invalid variant name `{name}`")))
    }
}

/// The feature inputs a model takes (`mcdenoise.features`): with or without light transport
/// covariance.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FeatureSet {
    Full,
    Nocov,
}

impl FeatureSet {
    pub const ALL: [FeatureSet; 2] = [FeatureSet::Full, FeatureSet::Nocov];

    pub fn name(self) -> &'static str {
        match self {
            FeatureSet::Full => "full",
            FeatureSet::Nocov => "nocov",
        }
    }

    pub fn features(self) -> &'static [&'static str] {
        match self {
            FeatureSet::Full => &FEATURES_FULL,
            FeatureSet::Nocov => &FEATURES_NOCOV,
        }
    }

    pub fn feature_channels(self) -> usize {
        self.features().len()
    }

    /// Whether the features include the covariance buffer.
    pub fn uses_covariance(self) -> bool {
        self == FeatureSet::Full
    }

    /// The set whose comma-separated names are `list`.
    pub fn from_list(list: &str) -> Option<FeatureSet> {
        FeatureSet::ALL.into_iter().find(|f| f.features().join(",") == list)
    }
}

impl std::str::FromStr for Variant {
    type Err = String;

    fn from_str(s: &str) -> Result<Variant, String> {
        Variant::parse(s).ok_or_else(|| {
            format!(
                "`{s}` is not a variant name (auto, or a directory name of up to {} letters, digits, _, -, .)",
                Variant::MAX_LEN
            )
        })
    }
}

/// The two networks of a variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Component {
    Diffuse,
    Specular,
}

impl Component {
    pub const ALL: [Component; 2] = [Component::Diffuse, Component::Specular];

    pub fn name(self) -> &'static str {
        match self {
            Component::Diffuse => "diffuse",
            Component::Specular => "specular",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nocov_is_full_without_covariance() {
        let filtered: Vec<&str> = FEATURES_FULL.iter().copied().filter(|f| !f.contains("covariance")).collect();
        assert_eq!(filtered, FEATURES_NOCOV);
    }

    #[test]
    fn variant_names_round_trip_and_bad_ones_are_refused() {
        assert_eq!(Variant::parse("full"), Some(Variant::Full));
        assert_eq!(Variant::Nocov.name(), "nocov");
        let v = Variant::parse("lin2020").unwrap();
        assert_eq!((v.name(), v.to_string()), ("lin2020", "lin2020".to_string()));
        assert_eq!(serde_json::to_string(&v).unwrap(), "\"lin2020\"");
        assert_eq!(serde_json::from_str::<Variant>("\"full\"").unwrap(), Variant::Full);
        assert!(serde_json::from_str::<Variant>("\"../x\"").is_err());
        let longest = "a".repeat(Variant::MAX_LEN);
        assert_eq!(Variant::parse(&longest).unwrap().name(), longest);
        for bad in ["", ".hidden", "a/b", "a b", "é", &"a".repeat(Variant::MAX_LEN + 1)] {
            assert_eq!(Variant::parse(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn feature_sets_are_found_from_their_list() {
        assert_eq!(FeatureSet::from_list(&FEATURES_FULL.join(",")), Some(FeatureSet::Full));
        assert_eq!(FeatureSet::from_list(&FEATURES_NOCOV.join(",")), Some(FeatureSet::Nocov));
        assert_eq!(FeatureSet::from_list("normal.R"), None);
    }

    #[test]
    fn a_files_precision_is_the_first_word_of_its_key() {
        assert_eq!(Precision::parse(None), Some(Precision::Fp32));
        assert_eq!(Precision::parse(Some("fp16")), Some(Precision::Fp16));
        let quantised = "int8 (QDQ all operators, per-channel weights; heads in float)";
        assert_eq!(Precision::parse(Some(quantised)), Some(Precision::Int8));
        assert_eq!(Precision::parse(Some("bf16")), None);
        // What the command line takes: no int8 there (quantised models are a directory).
        assert_eq!("fp16".parse::<Precision>(), Ok(Precision::Fp16));
        assert!("int8".parse::<Precision>().unwrap_err().contains("expected `auto`, `fp32` or `fp16`"));
    }
}
