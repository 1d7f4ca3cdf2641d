//! Model contract v1: what a model file must declare for the engine to use it.
//! The full text is `docs/model-contract.md`; `training/mcdenoise_train/contract.py` mirrors
//! these constants on the training side.

/// Version of the contract this engine implements.
pub const CONTRACT_VERSION: &str = "1";
/// Side of the predicted kernel.
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
}

/// Which inputs a model takes: with or without light transport covariance.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    Full,
    Nocov,
}

impl Variant {
    pub const ALL: [Variant; 2] = [Variant::Full, Variant::Nocov];

    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::Nocov => "nocov",
        }
    }

    pub fn parse(s: &str) -> Option<Variant> {
        Variant::ALL.into_iter().find(|v| v.name() == s)
    }

    pub fn features(self) -> &'static [&'static str] {
        match self {
            Variant::Full => &FEATURES_FULL,
            Variant::Nocov => &FEATURES_NOCOV,
        }
    }

    pub fn feature_channels(self) -> usize {
        self.features().len()
    }

    /// Whether the variant reads the covariance buffer.
    pub fn uses_covariance(self) -> bool {
        self == Variant::Full
    }

    /// A variant choice where `auto` (or nothing) lets the frame decide: `None`.
    pub fn parse_choice(s: &str) -> Result<Option<Variant>, String> {
        match s {
            "" | "auto" => Ok(None),
            other => other.parse().map(Some),
        }
    }
}

impl std::str::FromStr for Variant {
    type Err = String;

    fn from_str(s: &str) -> Result<Variant, String> {
        Variant::parse(s).ok_or_else(|| format!("unknown variant `{s}` (expected auto, full or nocov)"))
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
}
