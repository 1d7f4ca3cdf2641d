//! How a frame keeps its planes in memory.
//!
//! The colors the networks filter (diffuse, specular, color) and the depth stay f32. The
//! other buffers (albedo, normal, covariance and every variance) are kept as f16 when
//! every sample of the buffer lies within f16's range: that halves a frame's memory beyond
//! its colors (a 3840×2160 frame of 20 planes: 664 → 448 MB) and is exact for files that
//! store them as half, which is how renderers usually write auxiliary passes. From f32
//! files it rounds them to 11 significant bits (relative error at most 2⁻¹¹), well under
//! their own sampling noise; a buffer with a sample beyond ±65504 stays f32. Depth stays
//! f32 because its range is the scene's and its differences between neighbours are what
//! the networks read.

use half::{f16, slice::HalfFloatSliceExt};

use super::{Buffer, Plane};

/// The planes of one buffer, as stored.
#[derive(Clone, Debug)]
pub(crate) enum Stored {
    F32(Vec<Plane>),
    F16(Vec<Vec<f16>>),
}

impl Stored {
    /// `planes` of `buffer`, kept as f16 where [`Buffer::half_precision`] allows it and
    /// every sample fits (the samples are finite: frames are sanitised first).
    pub(crate) fn new(buffer: Buffer, planes: Vec<Plane>) -> Stored {
        let max = f16::MAX.to_f32();
        if !buffer.half_precision() || !planes.iter().flatten().all(|v| v.abs() <= max) {
            return Stored::F32(planes);
        }
        Stored::F16(planes.into_iter().map(|p| half_plane(&p)).collect())
    }

    /// `count` planes of `n` zeros, in the buffer's storage.
    pub(crate) fn zeros(buffer: Buffer, count: usize, n: usize) -> Stored {
        if buffer.half_precision() {
            Stored::F16(vec![vec![f16::ZERO; n]; count])
        } else {
            Stored::F32(vec![vec![0f32; n]; count])
        }
    }

    pub(crate) fn len(&self) -> usize {
        match self {
            Stored::F32(p) => p.len(),
            Stored::F16(p) => p.len(),
        }
    }

    pub(crate) fn plane(&self, c: usize) -> PlaneRef<'_> {
        match self {
            Stored::F32(p) => PlaneRef::F32(&p[c]),
            Stored::F16(p) => PlaneRef::F16(&p[c]),
        }
    }

    /// The planes as f32, converted if stored as f16.
    pub(crate) fn into_f32(self) -> Vec<Plane> {
        match self {
            Stored::F32(p) => p,
            Stored::F16(p) => p.iter().map(|p| PlaneRef::F16(p).to_vec()).collect(),
        }
    }
}

fn half_plane(p: &[f32]) -> Vec<f16> {
    let mut out = vec![f16::ZERO; p.len()];
    out.convert_from_f32_slice(p);
    out
}

/// One plane of a frame, row-major, whatever its storage ([`Stored`]).
#[derive(Clone, Copy, Debug)]
pub enum PlaneRef<'a> {
    F32(&'a [f32]),
    F16(&'a [f16]),
}

impl PlaneRef<'_> {
    pub fn len(&self) -> usize {
        match self {
            PlaneRef::F32(p) => p.len(),
            PlaneRef::F16(p) => p.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sample `i`.
    #[inline]
    pub fn get(&self, i: usize) -> f32 {
        match self {
            PlaneRef::F32(p) => p[i],
            PlaneRef::F16(p) => p[i].to_f32(),
        }
    }

    /// Samples `start .. start + out.len()` into `out` (f16 converted a vector at a time).
    pub fn read(&self, start: usize, out: &mut [f32]) {
        match self {
            PlaneRef::F32(p) => out.copy_from_slice(&p[start..][..out.len()]),
            PlaneRef::F16(p) => p[start..][..out.len()].convert_to_f32_slice(out),
        }
    }

    /// The plane as f32.
    pub fn to_vec(&self) -> Vec<f32> {
        let mut out = vec![0f32; self.len()];
        self.read(0, &mut out);
        out
    }

    /// The largest sample, or 0 when every sample is below 0.
    pub fn max(&self) -> f32 {
        match self {
            PlaneRef::F32(p) => p.iter().copied().fold(0f32, f32::max),
            PlaneRef::F16(p) => p.iter().map(|v| v.to_f32()).fold(0f32, f32::max),
        }
    }

    /// Whether any sample is not zero.
    pub fn any_nonzero(&self) -> bool {
        match self {
            PlaneRef::F32(p) => p.iter().any(|v| *v != 0.0),
            PlaneRef::F16(p) => p.iter().any(|v| v.to_f32() != 0.0),
        }
    }

    /// Where the samples are: two planes at one address are the same memory.
    pub fn as_ptr(&self) -> *const () {
        match self {
            PlaneRef::F32(p) => p.as_ptr().cast(),
            PlaneRef::F16(p) => p.as_ptr().cast(),
        }
    }

    /// Whether the plane is kept as f16.
    pub fn is_half(&self) -> bool {
        matches!(self, PlaneRef::F16(_))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn features_in_range_are_kept_as_f16_and_colors_and_depth_as_f32() {
        let p = vec![vec![0.25f32, -1.0, 65504.0]];
        assert!(matches!(Stored::new(Buffer::Normal, p.clone()), Stored::F16(_)));
        assert!(matches!(Stored::new(Buffer::DiffuseVariance, p.clone()), Stored::F16(_)));
        for b in [Buffer::Diffuse, Buffer::Specular, Buffer::Color, Buffer::Depth] {
            assert!(matches!(Stored::new(b, p.clone()), Stored::F32(_)), "{}", b.name());
        }
    }

    #[test]
    fn a_buffer_with_a_sample_beyond_f16_stays_f32_and_exact() {
        // A firefly's variance: f16 would make it infinite.
        let p = vec![vec![0.5f32; 4], vec![0.5, 1e6, 0.5, 0.5]];
        let s = Stored::new(Buffer::SpecularVariance, p.clone());
        assert!(matches!(s, Stored::F32(_)));
        assert_eq!(s.into_f32(), p);
    }

    #[test]
    fn f16_storage_rounds_to_eleven_significant_bits() {
        let p: Vec<f32> = (0..1000).map(|i| 0.001 + i as f32 * 0.0137).collect();
        let s = Stored::new(Buffer::Albedo, vec![p.clone()]);
        let back = s.plane(0);
        assert!(back.is_half());
        for (i, v) in p.iter().enumerate() {
            assert!((back.get(i) - v).abs() <= v.abs() * 2f32.powi(-11), "{v} -> {}", back.get(i));
        }
        let mut row = vec![0f32; 10];
        back.read(500, &mut row);
        assert_eq!(row, (500..510).map(|i| back.get(i)).collect::<Vec<_>>());
        assert_eq!(back.to_vec().len(), 1000);
        assert_eq!(back.max(), back.get(999));
    }

    #[test]
    fn half_samples_round_trip_exactly() {
        // What a file storing the pass as half holds.
        let p: Vec<f32> = [0.1f32, 3.7, -0.62, 1234.5, 0.0].iter().map(|v| f16::from_f32(*v).to_f32()).collect();
        assert_eq!(Stored::new(Buffer::Normal, vec![p.clone()]).into_f32(), vec![p]);
    }
}
