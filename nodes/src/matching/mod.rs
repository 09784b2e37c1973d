//! The `match` family: descriptor and patch matching between two views, and drawing matches.
//!
//! `match` is a Rust keyword, so the module is `matching`; operator ids are `match.*`:
//! - `match.brute_force` ([`brute_force`]): exact nearest neighbours with Lowe's ratio test,
//!   cross-check and spatial / epipolar restriction;
//! - `match.approximate` ([`approximate`]): randomized k-d forest (float) and hierarchical
//!   clustering trees (binary) with a `checks` budget;
//! - `match.patch` ([`patch`]): SSD / NCC / ZNCC patch search with subpixel peaks;
//! - `match.draw` ([`draw`]): two images side by side with match lines.
//!
//! This module holds what they share: descriptor checks, the distance definitions and the
//! two-nearest-neighbour bookkeeping with its tie rule (equal distances: lowest train index).

pub mod approximate;
pub mod brute_force;
pub mod draw;
#[cfg(target_arch = "x86_64")]
mod float_avx2;
pub mod patch;

use std::borrow::Cow;

use ocellus_engine::op::{Inputs, OpError};
use ocellus_engine::value::{Descriptors, Keypoint, Value};

ocellus_engine::param_enum! {
    /// Descriptor distance.
    pub enum Norm {
        /// L2 for float descriptors, Hamming for binary ones.
        Auto = "auto",
        /// Euclidean distance (binary descriptors are read as vectors of byte values).
        L2 = "l2",
        /// Squared Euclidean distance.
        L2Squared = "l2_squared",
        /// Number of differing bits (binary descriptors only).
        Hamming = "hamming",
    }
}

/// The distance actually used once the descriptor kind is known.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Metric {
    /// Euclidean, reported as `√d²`.
    L2,
    /// Squared Euclidean.
    L2Squared,
    /// Hamming bit count.
    Hamming,
}

impl Metric {
    /// The reported distance for a squared-L2 or Hamming value `d`.
    pub fn report(self, d: f64) -> f32 {
        match self {
            Metric::L2 => d.sqrt() as f32,
            Metric::L2Squared | Metric::Hamming => d as f32,
        }
    }
}

/// Descriptors in the form the matchers read: float rows or 64-bit word rows.
#[derive(Debug, Clone)]
pub enum DescriptorRows<'a> {
    /// `dim` floats per row.
    Float {
        /// Floats per row.
        dim: usize,
        /// Rows.
        data: Cow<'a, [f32]>,
    },
    /// `words` little-endian u64 words per row (the bytes, zero-padded to a multiple of 8).
    Binary {
        /// Words per row.
        words: usize,
        /// Rows.
        data: Vec<u64>,
    },
}

impl DescriptorRows<'_> {
    /// Number of rows.
    pub fn len(&self) -> usize {
        match self {
            DescriptorRows::Float { dim, data } => data.len().checked_div(*dim).unwrap_or(0),
            DescriptorRows::Binary { words, data } => data.len().checked_div(*words).unwrap_or(0),
        }
    }

    /// True without rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Exact distance (squared L2 or Hamming) between row `a` of `self` and row `b` of
    /// `other`, which must be of the same kind and width.
    pub fn distance(&self, a: usize, other: &DescriptorRows<'_>, b: usize) -> f64 {
        match (self, other) {
            (DescriptorRows::Float { dim, data }, DescriptorRows::Float { data: o, .. }) => {
                l2_squared_exact(&data[a * dim..(a + 1) * dim], &o[b * dim..(b + 1) * dim])
            }
            (DescriptorRows::Binary { words, data }, DescriptorRows::Binary { data: o, .. }) => {
                f64::from(hamming(
                    &data[a * words..(a + 1) * words],
                    &o[b * words..(b + 1) * words],
                ))
            }
            _ => f64::INFINITY,
        }
    }
}

/// Checks one descriptor set: whole rows, nonzero width, finite floats.
pub fn check_descriptors(port: &str, d: &Descriptors) -> Result<(), OpError> {
    match d {
        Descriptors::Float { dim, data } => {
            if *dim == 0 && !data.is_empty() {
                return Err(OpError::input(port, "float descriptors with dim 0"));
            }
            if *dim > 0 && data.len() % dim != 0 {
                return Err(OpError::input(
                    port,
                    format!(
                        "{} floats is not a whole number of {dim}-float rows",
                        data.len()
                    ),
                ));
            }
            if let Some(i) = data.iter().position(|v| !v.is_finite()) {
                return Err(OpError::input(
                    port,
                    format!("descriptor {} holds a non-finite value", i / dim.max(&1)),
                ));
            }
        }
        Descriptors::Binary { bytes, data } => {
            if *bytes == 0 && !data.is_empty() {
                return Err(OpError::input(
                    port,
                    "binary descriptors with 0 bytes per row",
                ));
            }
            if *bytes > 0 && data.len() % bytes != 0 {
                return Err(OpError::input(
                    port,
                    format!(
                        "{} bytes is not a whole number of {bytes}-byte rows",
                        data.len()
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Width of a descriptor set for messages: `128 floats` / `32 bytes`.
fn width_text(d: &Descriptors) -> String {
    match d {
        Descriptors::Float { dim, .. } => format!("float descriptors of {dim} floats"),
        Descriptors::Binary { bytes, .. } => format!("binary descriptors of {bytes} bytes"),
    }
}

/// Checks that `query` and `train` can be compared under `norm` and returns the metric and
/// both sets in matcher form. Callers handle empty sets before (they match nothing).
pub fn prepare<'a>(
    query: &'a Descriptors,
    train: &'a Descriptors,
    norm: Norm,
) -> Result<(Metric, DescriptorRows<'a>, DescriptorRows<'a>), OpError> {
    check_descriptors("query", query)?;
    check_descriptors("train", train)?;
    let same_width = match (query, train) {
        (Descriptors::Float { dim: a, .. }, Descriptors::Float { dim: b, .. }) => a == b,
        (Descriptors::Binary { bytes: a, .. }, Descriptors::Binary { bytes: b, .. }) => a == b,
        _ => false,
    };
    if !same_width {
        return Err(OpError::input(
            "train",
            format!(
                "query holds {}, train holds {}: both must be the same kind and width",
                width_text(query),
                width_text(train)
            ),
        ));
    }
    let binary = matches!(query, Descriptors::Binary { .. });
    let metric = match (norm, binary) {
        (Norm::Auto, false) | (Norm::L2, _) => Metric::L2,
        (Norm::L2Squared, _) => Metric::L2Squared,
        (Norm::Auto, true) | (Norm::Hamming, true) => Metric::Hamming,
        (Norm::Hamming, false) => {
            return Err(OpError::input(
                "query",
                "norm \"hamming\" needs binary descriptors, got float ones",
            ));
        }
    };
    let rows = |d: &'a Descriptors| match (d, metric) {
        (Descriptors::Float { dim, data }, _) => DescriptorRows::Float {
            dim: *dim,
            data: Cow::Borrowed(data.as_slice()),
        },
        (Descriptors::Binary { bytes, data }, Metric::Hamming) => DescriptorRows::Binary {
            words: bytes.div_ceil(8),
            data: pack_words(data, *bytes),
        },
        (Descriptors::Binary { bytes, data }, _) => DescriptorRows::Float {
            dim: *bytes,
            data: Cow::Owned(data.iter().map(|&b| f32::from(b)).collect()),
        },
    };
    Ok((metric, rows(query), rows(train)))
}

/// Packs rows of `bytes` bytes into little-endian u64 words, zero-padding each row.
pub fn pack_words(data: &[u8], bytes: usize) -> Vec<u64> {
    if bytes == 0 {
        return Vec::new();
    }
    let words = bytes.div_ceil(8);
    let mut out = Vec::with_capacity(data.len() / bytes * words);
    for row in data.chunks_exact(bytes) {
        for chunk in row.chunks(8) {
            let mut w = [0u8; 8];
            w[..chunk.len()].copy_from_slice(chunk);
            out.push(u64::from_le_bytes(w));
        }
    }
    out
}

/// Hamming distance between two word rows.
#[inline]
pub fn hamming(a: &[u64], b: &[u64]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

/// The exact squared L2 distance every matcher reports and compares: differences and squares in
/// f64, summed in four interleaved partial sums (lane `i mod 4`) added as `(s0 + s1) + (s2 +
/// s3)`. A fixed order, so the value is the same wherever it is computed.
#[inline]
pub fn l2_squared_exact(a: &[f32], b: &[f32]) -> f64 {
    let mut s = [0.0f64; 4];
    let mut ca = a.chunks_exact(4);
    let mut cb = b.chunks_exact(4);
    for (x, y) in (&mut ca).zip(&mut cb) {
        for l in 0..4 {
            let d = f64::from(x[l]) - f64::from(y[l]);
            s[l] += d * d;
        }
    }
    for (l, (x, y)) in ca.remainder().iter().zip(cb.remainder()).enumerate() {
        let d = f64::from(*x) - f64::from(*y);
        s[l] += d * d;
    }
    (s[0] + s[1]) + (s[2] + s[3])
}

/// The two nearest neighbours found so far; ties go to the lower index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Top2 {
    /// Nearest distance (squared L2 or Hamming).
    pub d1: f64,
    /// Its index, `u32::MAX` if none.
    pub i1: u32,
    /// Second distance.
    pub d2: f64,
    /// Its index, `u32::MAX` if none.
    pub i2: u32,
}

impl Default for Top2 {
    fn default() -> Self {
        Top2 {
            d1: f64::INFINITY,
            i1: u32::MAX,
            d2: f64::INFINITY,
            i2: u32::MAX,
        }
    }
}

impl Top2 {
    /// Offers candidate `i` at distance `d` (any order of indices): ordered by `(d, i)`.
    #[inline]
    pub fn offer(&mut self, d: f64, i: u32) {
        if (d, i) < (self.d2, self.i2) {
            if (d, i) < (self.d1, self.i1) {
                self.d2 = self.d1;
                self.i2 = self.i1;
                self.d1 = d;
                self.i1 = i;
            } else if i != self.i1 {
                self.d2 = d;
                self.i2 = i;
            }
        }
    }

    /// True if a nearest neighbour was found.
    pub fn found(&self) -> bool {
        self.i1 != u32::MAX
    }
}

/// Lowe's ratio test on reported distances, OpenCV's convention: accepted if `d1 < ratio · d2`
/// (in f64 on the f32 distances); `ratio ≥ 1` or a missing second neighbour accepts.
pub fn ratio_accepts(top: &Top2, metric: Metric, ratio: f64) -> bool {
    if ratio >= 1.0 || top.i2 == u32::MAX {
        return true;
    }
    f64::from(metric.report(top.d1)) < ratio * f64::from(metric.report(top.d2))
}

/// The optional keypoints on `port`, checked to have `count` entries.
pub fn optional_keypoints<'a>(
    inputs: &Inputs<'a>,
    port: &str,
    count: usize,
) -> Result<Option<&'a [Keypoint]>, OpError> {
    match inputs.get(port) {
        None => Ok(None),
        Some(Value::Keypoints(k)) => {
            if k.len() != count {
                return Err(OpError::input(
                    port,
                    format!("{} keypoints for {count} descriptors", k.len()),
                ));
            }
            Ok(Some(k.as_slice()))
        }
        Some(other) => Err(OpError::input(
            port,
            format!("expected Keypoints, got {}", other.port_type()),
        )),
    }
}

/// The descriptors on required port `port`.
pub fn descriptors<'a>(inputs: &Inputs<'a>, port: &str) -> Result<&'a Descriptors, OpError> {
    match inputs.require(port)? {
        Value::Descriptors(d) => Ok(d),
        other => Err(OpError::input(
            port,
            format!("expected Descriptors, got {}", other.port_type()),
        )),
    }
}

/// The keypoints on required port `port`.
pub fn keypoints<'a>(inputs: &Inputs<'a>, port: &str) -> Result<&'a [Keypoint], OpError> {
    match inputs.require(port)? {
        Value::Keypoints(k) => Ok(k),
        other => Err(OpError::input(
            port,
            format!("expected Keypoints, got {}", other.port_type()),
        )),
    }
}

/// The matches on required port `port`.
pub fn matches<'a>(
    inputs: &Inputs<'a>,
    port: &str,
) -> Result<&'a [ocellus_engine::value::Match], OpError> {
    match inputs.require(port)? {
        Value::Matches(m) => Ok(m),
        other => Err(OpError::input(
            port,
            format!("expected Matches, got {}", other.port_type()),
        )),
    }
}

#[cfg(test)]
pub(crate) mod test_support {
    use ocellus_engine::value::Descriptors;

    /// A deterministic xorshift stream.
    pub fn stream(seed: u64) -> impl FnMut() -> u64 {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        }
    }

    /// `n` random binary descriptors of `bytes` bytes.
    pub fn random_binary(n: usize, bytes: usize, seed: u64) -> Descriptors {
        let mut next = stream(seed);
        Descriptors::Binary {
            bytes,
            data: (0..n * bytes).map(|_| next() as u8).collect(),
        }
    }

    /// `n` random float descriptors of `dim` values in 0..1 with `levels` distinct values (few
    /// levels give ties).
    pub fn random_float(n: usize, dim: usize, levels: u64, seed: u64) -> Descriptors {
        let mut next = stream(seed);
        Descriptors::Float {
            dim,
            data: (0..n * dim)
                .map(|_| (next() % levels) as f32 / levels as f32)
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hamming_hand_cases() {
        assert_eq!(hamming(&[0], &[0]), 0);
        assert_eq!(hamming(&[u64::MAX], &[0]), 64);
        assert_eq!(hamming(&[0b1011, 1 << 63], &[0b0001, 0]), 3);
        let w = pack_words(&[0xFF, 0x01, 0x80], 3);
        assert_eq!(w, vec![0x80_01_FF]);
        assert_eq!(hamming(&w, &[0]), 10);
        // 9-byte rows pad to two words.
        let w = pack_words(&[1, 0, 0, 0, 0, 0, 0, 0, 3, 2, 0, 0, 0, 0, 0, 0, 0, 1], 9);
        assert_eq!(w, vec![1, 3, 2, 1]);
        assert_eq!(hamming(&w[..2], &w[2..]), 2 + 1);
    }

    #[test]
    fn top2_orders_by_distance_then_index() {
        let mut t = Top2::default();
        t.offer(5.0, 7);
        t.offer(5.0, 3);
        t.offer(5.0, 9);
        assert_eq!((t.d1, t.i1, t.d2, t.i2), (5.0, 3, 5.0, 7));
        t.offer(1.0, 10);
        assert_eq!((t.i1, t.i2), (10, 3));
        t.offer(1.0, 10);
        assert_eq!((t.i1, t.i2), (10, 3));
    }

    #[test]
    fn exact_l2_hand_case() {
        assert_eq!(
            l2_squared_exact(&[1.0, 2.0, 3.0, 4.0, 5.0], &[0.0; 5]),
            55.0
        );
        assert_eq!(l2_squared_exact(&[], &[]), 0.0);
    }

    #[test]
    fn prepare_checks_widths_and_norms() {
        let f = Descriptors::Float {
            dim: 4,
            data: vec![0.0; 8],
        };
        let g = Descriptors::Float {
            dim: 2,
            data: vec![0.0; 8],
        };
        let b = Descriptors::Binary {
            bytes: 4,
            data: vec![0; 8],
        };
        let e = prepare(&f, &g, Norm::Auto).unwrap_err().to_string();
        assert!(e.contains("4 floats") && e.contains("2 floats"), "{e}");
        assert!(prepare(&f, &b, Norm::Auto).is_err());
        assert!(prepare(&f, &f, Norm::Hamming).is_err());
        assert_eq!(prepare(&b, &b, Norm::Auto).unwrap().0, Metric::Hamming);
        assert_eq!(prepare(&b, &b, Norm::L2).unwrap().0, Metric::L2);
        let nan = Descriptors::Float {
            dim: 2,
            data: vec![0.0, f32::NAN],
        };
        assert!(prepare(&nan, &nan, Norm::Auto).is_err());
        let ragged = Descriptors::Binary {
            bytes: 3,
            data: vec![0; 4],
        };
        assert!(prepare(&ragged, &ragged, Norm::Auto).is_err());
    }
}
