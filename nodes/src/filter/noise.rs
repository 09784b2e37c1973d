//! `filter.noise`: additive Gaussian noise, salt-and-pepper noise and Poisson (shot) noise, all
//! reproducible from a seed.
//!
//! Random numbers are counter-based: the value for sample (or pixel) `i` is a hash of
//! `(seed, kind, i)` (splitmix64's output function on `key + (i + 1)·φ`, φ the 64-bit golden
//! ratio), never drawn from a generator shared between threads. Each sample's noise therefore
//! depends only on the seed and its index, and the output is bit-identical for any thread
//! count and any split of the work. Poisson samples that need several uniforms draw them from a
//! splitmix64 stream seeded by that hash.

use std::f32::consts::TAU;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

/// Pixels per parallel task (even, so Gaussian pairs never straddle two tasks).
const CHUNK_PIXELS: usize = 8192;

/// splitmix64's increment, ⌊2⁶⁴/φ⌋.
const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// Per-kind salts, so the kinds draw unrelated numbers from the same seed.
const SALT_GAUSSIAN: u64 = 0x6761_7573_7369_616E;
const SALT_IMPULSE: u64 = 0x696D_7075_6C73_6531;
const SALT_POLARITY: u64 = 0x696D_7075_6C73_6532;
const SALT_POISSON: u64 = 0x706F_6973_736F_6E21;

/// Below this mean, Poisson samples are drawn by inversion (sequential search of the CDF);
/// from it on, by PTRS.
pub const POISSON_INVERSION_LIMIT: f64 = 10.0;

param_enum! {
    /// Noise model.
    pub enum NoiseKind {
        /// Additive white Gaussian noise of standard deviation `sigma`.
        Gaussian = "gaussian",
        /// Impulse noise: a fraction `amount` of pixels set to the maximum or minimum value.
        SaltPepper = "salt_pepper",
        /// Shot noise: out = Poisson(in · scale) / scale.
        Poisson = "poisson",
    }
}

params! {
    /// Parameters of `filter.noise`.
    pub struct NoiseParams {
        /// Noise model: "gaussian", "salt_pepper" or "poisson".
        kind: NoiseKind = NoiseKind::Gaussian,
        /// Seed; the same seed and image give the same output.
        seed: u64 = 0,
        /// "gaussian": standard deviation in the image's units (gray levels for u8 and u16,
        /// absolute for f32, e.g. 0.04 for an image in 0..1), ≥ 0.
        sigma: f64 = 10.0 => [min = 0.0],
        /// "salt_pepper": fraction of pixels replaced, 0..=1.
        amount: f64 = 0.05 => [min = 0.0, max = 1.0],
        /// "salt_pepper": fraction of the replaced pixels that become salt (maximum), 0..=1.
        salt_ratio: f64 = 0.5 => [min = 0.0, max = 1.0],
        /// "poisson": photons per unit of sample value (> 0): a u8 sample v has mean photon
        /// count λ = v·scale; larger means less noise (relative noise 1/√λ).
        scale: f64 = 1.0 => [above = 0.0, unit = "photons/unit"],
    }
}

/// Seeded noise (`filter.noise`). See [`add_noise`].
#[derive(Debug, Clone, PartialEq)]
pub struct Noise {
    model: NoiseModel,
    seed: u64,
}

/// A noise model with its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NoiseModel {
    /// Additive Gaussian noise of this standard deviation (image units).
    Gaussian {
        /// Standard deviation.
        sigma: f64,
    },
    /// Salt and pepper.
    SaltPepper {
        /// Fraction of pixels replaced.
        amount: f64,
        /// Fraction of those set to the maximum.
        salt_ratio: f64,
    },
    /// Poisson shot noise.
    Poisson {
        /// Photons per unit.
        scale: f64,
    },
}

impl Op for Noise {
    type Params = NoiseParams;
    const ID: &'static str = "filter.noise";
    const SUMMARY: &'static str =
        "Adds reproducible Gaussian, salt-and-pepper or Poisson (shot) noise to an image.";
    const DOC: &'static str = r#"
Adds seeded noise; the output has the input's pixel format (u8/u16 rounded to nearest and
saturated). The alpha channel of RGBA images is left unchanged.
- gaussian: out = in + sigma·z, z standard normal, independent per sample (Box–Muller on 24-bit
  uniforms, so |z| ≤ 5.77; the tail beyond has probability 8·10⁻⁹).
- salt_pepper: each pixel is replaced with probability `amount`, by the maximum (255, 65535, or
  1.0 for f32) with probability `salt_ratio`, else by 0; all colour channels of a pixel together.
- poisson: out = k/scale with k ~ Poisson(λ = in·scale) per sample, so the mean is the input
  and the variance in/scale. Negative or zero λ gives 0; NaN and infinite samples pass through.
  λ < 10: inversion by sequential search; λ ≥ 10: Hörmann's PTRS (transformed rejection with
  squeeze), as numpy.

Reproducible: every sample's random numbers are a hash of (seed, sample index) (counter-based,
splitmix64's mixing function), so the result depends on the seed and never on the thread count.
Different from OpenCV's `randn`/`randu` streams (no bit-for-bit match with any library).

Reference: G. E. P. Box, M. E. Muller, "A note on the generation of random normal deviates",
Ann. Math. Stat. 29 (1958); W. Hörmann, "The transformed rejection method for generating
Poisson random variables", Insurance: Mathematics and Economics 12 (1993); G. Steele, D. Lea,
C. Flood, "Fast splittable pseudorandom number generators", OOPSLA 2014 (splitmix64).

Example:
    "noisy": (op: "filter.noise", inputs: { "image": "card.image" }, params: (kind: "gaussian", sigma: 8.0, seed: 42)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to add noise to, any pixel format.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The noisy image, same size and pixel format as the input.",
        )]
    }

    fn new(params: NoiseParams) -> Result<Self, String> {
        let NoiseParams {
            kind,
            seed,
            sigma,
            amount,
            salt_ratio,
            scale,
        } = params;
        if !(sigma >= 0.0 && sigma.is_finite()) {
            return Err(format!("`sigma` must be finite and ≥ 0, got {sigma}"));
        }
        for (name, value) in [("amount", amount), ("salt_ratio", salt_ratio)] {
            if !(0.0..=1.0).contains(&value) {
                return Err(format!("`{name}` must be between 0 and 1, got {value}"));
            }
        }
        if !(scale > 0.0 && scale.is_finite()) {
            return Err(format!("`scale` must be finite and > 0, got {scale}"));
        }
        let model = match kind {
            NoiseKind::Gaussian => NoiseModel::Gaussian { sigma },
            NoiseKind::SaltPepper => NoiseModel::SaltPepper { amount, salt_ratio },
            NoiseKind::Poisson => NoiseModel::Poisson { scale },
        };
        Ok(Noise { model, seed })
    }
}

impl Operator for Noise {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        Ok(Outputs::new().with(
            "image",
            Value::image(add_noise(image, self.model, self.seed)),
        ))
    }
}

/// `image` with noise of `model` drawn from `seed` (see the operator docs); same format.
pub fn add_noise(image: &Image, model: NoiseModel, seed: u64) -> Image {
    let channels = image.channels();
    let data = match image.data() {
        PixelData::U8(v) => PixelData::U8(noisy(v, channels, model, seed)),
        PixelData::U16(v) => PixelData::U16(noisy(v, channels, model, seed)),
        PixelData::F32(v) => PixelData::F32(noisy(v, channels, model, seed)),
    };
    Image::new(image.width(), image.height(), channels, data).unwrap_or_else(|_| image.clone())
}

/// A sample type noise is added to.
trait Sample: Copy + Send + Sync {
    /// Salt value.
    const MAX: Self;
    /// Pepper value.
    const MIN: Self;
    fn to_f64(self) -> f64;
    fn to_f32(self) -> f32;
    /// Rounded and saturated for integers.
    fn from_f32(v: f32) -> Self;
    fn from_f64(v: f64) -> Self;
}

impl Sample for u8 {
    const MAX: u8 = u8::MAX;
    const MIN: u8 = 0;
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
    fn from_f32(v: f32) -> u8 {
        v.round() as u8
    }
    fn from_f64(v: f64) -> u8 {
        v.round() as u8
    }
}

impl Sample for u16 {
    const MAX: u16 = u16::MAX;
    const MIN: u16 = 0;
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
    fn from_f32(v: f32) -> u16 {
        v.round() as u16
    }
    fn from_f64(v: f64) -> u16 {
        v.round() as u16
    }
}

impl Sample for f32 {
    const MAX: f32 = 1.0;
    const MIN: f32 = 0.0;
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn to_f32(self) -> f32 {
        self
    }
    fn from_f32(v: f32) -> f32 {
        v
    }
    fn from_f64(v: f64) -> f32 {
        v as f32
    }
}

fn noisy<T: Sample>(src: &[T], channels: Channels, model: NoiseModel, seed: u64) -> Vec<T> {
    let ch = channels.count();
    // Channels that get noise: all but the alpha of RGBA.
    let noisy_channels = if channels == Channels::Rgba { 3 } else { ch };
    let mut dst = src.to_vec();
    let chunk = CHUNK_PIXELS * ch;
    match model {
        NoiseModel::Gaussian { sigma } => {
            let key = mix(seed ^ SALT_GAUSSIAN);
            let sigma = sigma as f32;
            dst.par_chunks_mut(chunk).enumerate().for_each_init(
                || vec![0.0f32; chunk],
                |z, (k, out)| {
                    let first = k * chunk;
                    let z = &mut z[..out.len().next_multiple_of(2)];
                    gaussian_pairs(key, first / 2, z);
                    if noisy_channels == ch {
                        for (o, &z) in out.iter_mut().zip(z.iter()) {
                            *o = T::from_f32(o.to_f32() + sigma * z);
                        }
                    } else {
                        for (px, zs) in out.chunks_exact_mut(ch).zip(z.chunks_exact(ch)) {
                            for (o, &z) in px[..noisy_channels].iter_mut().zip(zs) {
                                *o = T::from_f32(o.to_f32() + sigma * z);
                            }
                        }
                    }
                },
            );
        }
        NoiseModel::SaltPepper { amount, salt_ratio } => {
            let impulse = mix(seed ^ SALT_IMPULSE);
            let polarity = mix(seed ^ SALT_POLARITY);
            dst.par_chunks_mut(chunk).enumerate().for_each(|(k, out)| {
                let first = k * CHUNK_PIXELS;
                for (p, px) in out.chunks_exact_mut(ch).enumerate() {
                    let index = (first + p) as u64;
                    if unit_f64(hash(impulse, index)) < amount {
                        let value = if unit_f64(hash(polarity, index)) < salt_ratio {
                            T::MAX
                        } else {
                            T::MIN
                        };
                        px[..noisy_channels].fill(value);
                    }
                }
            });
        }
        NoiseModel::Poisson { scale } => {
            let key = mix(seed ^ SALT_POISSON);
            dst.par_chunks_mut(chunk).enumerate().for_each(|(k, out)| {
                let first = k * chunk;
                for (p, px) in out.chunks_exact_mut(ch).enumerate() {
                    for (c, o) in px[..noisy_channels].iter_mut().enumerate() {
                        let index = (first + p * ch + c) as u64;
                        let v = o.to_f64();
                        let lambda = v * scale;
                        if !lambda.is_finite() {
                            continue;
                        }
                        let count = if lambda > 0.0 {
                            poisson(lambda, &mut SplitMix(hash(key, index)))
                        } else {
                            0.0
                        };
                        *o = T::from_f64(count / scale);
                    }
                }
            });
        }
    }
    dst
}

/// splitmix64's output function (a bijective 64-bit mixer).
#[inline]
pub(crate) fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The `index`-th output of splitmix64 started at `key`: the random bits of one counter.
#[inline]
pub(crate) fn hash(key: u64, index: u64) -> u64 {
    mix(key.wrapping_add(index.wrapping_add(1).wrapping_mul(GOLDEN)))
}

/// Uniform in [0, 1) with 53 random bits.
#[inline]
pub(crate) fn unit_f64(bits: u64) -> f64 {
    (bits >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Standard normal deviates for samples `2·first_pair ..`, two per counter (Box–Muller: the
/// cosine branch for the even sample, the sine branch for the odd one). `z.len()` is even.
pub(crate) fn gaussian_pairs(key: u64, first_pair: usize, z: &mut [f32]) {
    const UNIT: f32 = 1.0 / (1u32 << 24) as f32;
    for (j, pair) in z.chunks_exact_mut(2).enumerate() {
        let bits = hash(key, (first_pair + j) as u64);
        // u1 in (0, 1], u2 in [0, 1), 24 bits each.
        let u1 = ((bits >> 40) + 1) as f32 * UNIT;
        let u2 = ((bits >> 16) & 0xFF_FFFF) as f32 * UNIT;
        let r = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (TAU * u2).sin_cos();
        pair[0] = r * c;
        pair[1] = r * s;
    }
}

/// A splitmix64 stream, for samples that need several uniforms.
pub(crate) struct SplitMix(pub(crate) u64);

impl SplitMix {
    fn next_f64(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(GOLDEN);
        unit_f64(mix(self.0))
    }
}

/// ln(k!) for a non-negative integer `k` (as f64): exact sum below 10, Stirling's series with
/// three correction terms from 10 on (error below 10⁻¹⁰).
fn ln_factorial(k: f64) -> f64 {
    if k < 10.0 {
        (2..=(k as u32)).map(|i| f64::from(i).ln()).sum()
    } else {
        let k2 = k * k;
        k * k.ln() - k
            + 0.5 * (std::f64::consts::TAU * k).ln()
            + (1.0 / 12.0 - (1.0 / 360.0 - 1.0 / (1260.0 * k2)) / k2) / k
    }
}

/// A Poisson deviate of mean `lambda` (finite, > 0), as f64.
pub(crate) fn poisson(lambda: f64, rng: &mut SplitMix) -> f64 {
    if lambda < POISSON_INVERSION_LIMIT {
        // Sequential search of the CDF.
        let mut u = rng.next_f64();
        let mut p = (-lambda).exp();
        let mut k = 0.0;
        while u > p && k < 200.0 {
            u -= p;
            k += 1.0;
            p *= lambda / k;
        }
        return k;
    }
    // PTRS (Hörmann 1993).
    let slam = lambda.sqrt();
    let loglam = lambda.ln();
    let b = 0.931 + 2.53 * slam;
    let a = -0.059 + 0.02483 * b;
    let inv_alpha = 1.1239 + 1.1328 / (b - 3.4);
    let vr = 0.9277 - 3.6224 / (b - 2.0);
    // The acceptance rate is above 85 %; the cap only guards against a broken stream.
    for _ in 0..1000 {
        let u = rng.next_f64() - 0.5;
        let v = rng.next_f64();
        let us = 0.5 - u.abs();
        let k = ((2.0 * a / us + b) * u + lambda + 0.43).floor();
        if us >= 0.07 && v <= vr {
            return k;
        }
        // k is NaN or −∞ when us = 0.
        if k.is_nan() || k < 0.0 || (us < 0.013 && v > us) {
            continue;
        }
        if v.ln() + inv_alpha.ln() - (a / (us * us) + b).ln()
            <= -lambda + k * loglam - ln_factorial(k)
        {
            return k;
        }
    }
    lambda.round()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::random_u8;
    use proptest::prelude::*;

    fn gray_f32(w: usize, h: usize, value: f32) -> Image {
        Image::from_f32(w, h, Channels::Gray, vec![value; w * h]).unwrap()
    }

    fn mean_var(v: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
        let n = v.clone().count() as f64;
        let mean = v.clone().sum::<f64>() / n;
        let var = v.map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
        (mean, var)
    }

    #[test]
    fn gaussian_has_the_requested_mean_and_variance() {
        let n = 200_000;
        let img = gray_f32(n, 1, 5.0);
        let out = add_noise(&img, NoiseModel::Gaussian { sigma: 2.0 }, 7);
        let (mean, var) = mean_var(out.as_f32().unwrap().iter().map(|&v| f64::from(v)));
        // Standard errors: mean 2/√n ≈ 0.0045, variance 4·√(2/n) ≈ 0.0126; allow 5 of them.
        assert!((mean - 5.0).abs() < 0.023, "mean {mean}");
        assert!((var - 4.0).abs() < 0.064, "variance {var}");
        // Even and odd samples (cosine and sine branches) are uncorrelated.
        let v = out.as_f32().unwrap();
        let cov: f64 = v
            .chunks_exact(2)
            .map(|p| (f64::from(p[0]) - 5.0) * (f64::from(p[1]) - 5.0))
            .sum::<f64>()
            / (n / 2) as f64;
        assert!(cov.abs() < 0.06, "covariance {cov}");
        // Fraction beyond 2σ ≈ 4.55 %.
        let tail = v.iter().filter(|&&x| (x - 5.0).abs() > 4.0).count() as f64 / n as f64;
        assert!((tail - 0.0455).abs() < 0.003, "tail {tail}");
    }

    #[test]
    fn gaussian_on_u8_rounds_and_saturates() {
        let img = Image::from_u8(1000, 1, Channels::Gray, vec![0; 1000]).unwrap();
        let out = add_noise(&img, NoiseModel::Gaussian { sigma: 20.0 }, 1);
        let v = out.as_u8().unwrap();
        let zeros = v.iter().filter(|&&x| x == 0).count();
        // About half the samples go negative and saturate at 0.
        assert!((400..600).contains(&zeros), "{zeros}");
        let img = Image::from_u16(3, 2, Channels::Rgb, vec![65535; 18]).unwrap();
        let out = add_noise(&img, NoiseModel::Gaussian { sigma: 0.0 }, 1);
        assert_eq!(out, img);
    }

    #[test]
    fn poisson_mean_equals_variance() {
        for lambda in [0.5, 3.0, 9.9, 10.0, 30.0, 1000.0] {
            let n = 100_000;
            let img = gray_f32(n, 1, lambda as f32);
            let out = add_noise(&img, NoiseModel::Poisson { scale: 1.0 }, 3);
            let v = out.as_f32().unwrap();
            assert!(v.iter().all(|&x| x >= 0.0 && x.fract() == 0.0));
            let (mean, var) = mean_var(v.iter().map(|&x| f64::from(x)));
            let se_mean = (lambda / n as f64).sqrt();
            // Var of the sample variance ≈ (λ + 2λ²)/n for a Poisson.
            let se_var = ((lambda + 2.0 * lambda * lambda) / n as f64).sqrt();
            assert!(
                (mean - lambda).abs() < 5.0 * se_mean,
                "λ {lambda}: mean {mean}"
            );
            assert!(
                (var - lambda).abs() < 5.0 * se_var,
                "λ {lambda}: variance {var}"
            );
        }
    }

    #[test]
    fn poisson_probabilities_match_the_pmf() {
        // λ = 12 (PTRS): P(k) for k = 5..=20 within 5 standard errors.
        let n = 200_000;
        let lambda = 12.0;
        let out = add_noise(
            &gray_f32(n, 1, 12.0),
            NoiseModel::Poisson { scale: 1.0 },
            11,
        );
        let mut counts = [0usize; 64];
        for &x in out.as_f32().unwrap() {
            counts[(x as usize).min(63)] += 1;
        }
        for (k, &count) in counts.iter().enumerate().take(21).skip(5) {
            let p = (-lambda + k as f64 * f64::ln(lambda) - ln_factorial(k as f64)).exp();
            let got = count as f64 / n as f64;
            let se = (p * (1.0 - p) / n as f64).sqrt();
            assert!((got - p).abs() < 5.0 * se, "P({k}) = {got}, expected {p}");
        }
    }

    #[test]
    fn poisson_scale_and_special_values() {
        // scale 100: out = Poisson(100·v)/100, mean v, variance v/100.
        let n = 50_000;
        let out = add_noise(
            &gray_f32(n, 1, 0.5),
            NoiseModel::Poisson { scale: 100.0 },
            2,
        );
        let (mean, var) = mean_var(out.as_f32().unwrap().iter().map(|&x| f64::from(x)));
        assert!((mean - 0.5).abs() < 0.002, "{mean}");
        assert!((var - 0.005).abs() < 0.0004, "{var}");
        let img = Image::from_f32(
            4,
            1,
            Channels::Gray,
            vec![0.0, -3.0, f32::NAN, f32::INFINITY],
        )
        .unwrap();
        let out = add_noise(&img, NoiseModel::Poisson { scale: 1.0 }, 0);
        let v = out.as_f32().unwrap();
        assert_eq!(v[..2], [0.0, 0.0]);
        assert!(v[2].is_nan() && v[3] == f32::INFINITY);
        // u8 saturates at 255.
        let img = Image::from_u8(100, 1, Channels::Gray, vec![250; 100]).unwrap();
        let out = add_noise(&img, NoiseModel::Poisson { scale: 1.0 }, 0);
        assert!(out.as_u8().unwrap().contains(&255));
    }

    #[test]
    fn ln_factorial_is_accurate() {
        let mut exact = 0.0f64;
        for k in 1..=40u32 {
            exact += f64::from(k).ln();
            assert!(
                (ln_factorial(f64::from(k)) - exact).abs() < 1e-9 * exact.max(1.0),
                "{k}"
            );
        }
        assert_eq!(ln_factorial(0.0), 0.0);
    }

    #[test]
    fn salt_and_pepper_fraction_and_alpha() {
        let (w, h) = (400, 250);
        let img = Image::from_u8(w, h, Channels::Rgba, vec![128; w * h * 4]).unwrap();
        let model = NoiseModel::SaltPepper {
            amount: 0.2,
            salt_ratio: 0.25,
        };
        let out = add_noise(&img, model, 9);
        let mut salt = 0;
        let mut pepper = 0;
        for px in out.as_u8().unwrap().chunks_exact(4) {
            assert_eq!(px[3], 128, "alpha is kept");
            match px[..3] {
                [255, 255, 255] => salt += 1,
                [0, 0, 0] => pepper += 1,
                [128, 128, 128] => {}
                _ => panic!("mixed pixel {px:?}"),
            }
        }
        let n = (w * h) as f64;
        let replaced = (salt + pepper) as f64 / n;
        // Standard error √(0.2·0.8/n) ≈ 0.0013.
        assert!((replaced - 0.2).abs() < 0.0065, "{replaced}");
        let ratio = salt as f64 / (salt + pepper) as f64;
        assert!((ratio - 0.25).abs() < 0.015, "{ratio}");
        // f32 salt is 1.0; amount 0 changes nothing, amount 1 everything.
        let img = gray_f32(50, 2, 0.5);
        let all = add_noise(
            &img,
            NoiseModel::SaltPepper {
                amount: 1.0,
                salt_ratio: 1.0,
            },
            0,
        );
        assert!(all.as_f32().unwrap().iter().all(|&v| v == 1.0));
        let none = add_noise(
            &img,
            NoiseModel::SaltPepper {
                amount: 0.0,
                salt_ratio: 1.0,
            },
            0,
        );
        assert_eq!(none, img);
    }

    #[test]
    fn seeds_are_reproducible_and_distinct() {
        let img = random_u8(64, 48, Channels::Rgb, 1);
        for model in [
            NoiseModel::Gaussian { sigma: 10.0 },
            NoiseModel::SaltPepper {
                amount: 0.1,
                salt_ratio: 0.5,
            },
            NoiseModel::Poisson { scale: 0.5 },
        ] {
            let a = add_noise(&img, model, 5);
            assert_eq!(a, add_noise(&img, model, 5), "{model:?}");
            assert_ne!(a, add_noise(&img, model, 6), "{model:?}");
            assert_ne!(a, img, "{model:?}");
        }
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        // Several chunks, and an odd sample count.
        let img = random_u8(331, 101, Channels::Rgb, 2);
        let float = Image::from_f32(
            301,
            99,
            Channels::Gray,
            img.as_u8().unwrap()[..301 * 99]
                .iter()
                .map(|&v| f32::from(v) / 255.0)
                .collect(),
        )
        .unwrap();
        for model in [
            NoiseModel::Gaussian { sigma: 10.0 },
            NoiseModel::SaltPepper {
                amount: 0.1,
                salt_ratio: 0.5,
            },
            NoiseModel::Poisson { scale: 30.0 },
        ] {
            for image in [&img, &float] {
                let run = || add_noise(image, model, 77);
                assert_eq!(pool(1).install(run), pool(3).install(run), "{model:?}");
            }
        }
    }

    #[test]
    fn params_are_checked_and_operator_runs() {
        let p = |f: fn(&mut NoiseParams)| {
            let mut p = NoiseParams::default();
            f(&mut p);
            Noise::new(p)
        };
        assert!(p(|_| ()).is_ok());
        assert!(p(|p| p.sigma = -1.0).unwrap_err().contains("sigma"));
        assert!(p(|p| p.sigma = f64::NAN).is_err());
        assert!(p(|p| p.amount = 1.5).unwrap_err().contains("amount"));
        assert!(
            p(|p| p.salt_ratio = f64::NAN)
                .unwrap_err()
                .contains("salt_ratio")
        );
        assert!(p(|p| p.scale = 0.0).unwrap_err().contains("scale"));
        assert!(p(|p| p.scale = f64::INFINITY).is_err());
        let op = p(|p| {
            p.kind = NoiseKind::Poisson;
            p.seed = 3;
        })
        .unwrap();
        let img = random_u8(9, 4, Channels::Gray, 1);
        let specs = Noise::inputs();
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let mut out = op
            .run(
                &ctx,
                &Inputs::new(&specs, &[Some(Value::image(img.clone()))]),
            )
            .unwrap();
        let Some(Value::Image(got)) = out.take("image") else {
            panic!("expected an image");
        };
        assert_eq!(*got, add_noise(&img, NoiseModel::Poisson { scale: 1.0 }, 3));
        let empty = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(
            add_noise(&empty, NoiseModel::Gaussian { sigma: 1.0 }, 0),
            empty
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        #[test]
        fn noise_of_a_sample_depends_only_on_its_index(
            w in 1usize..40,
            extra in 1usize..30,
            seed in any::<u64>(),
        ) {
            // A prefix of a longer image gets the same noise as the shorter image.
            let short = gray_f32(w, 1, 100.0);
            let long = gray_f32(w + extra, 1, 100.0);
            for model in [NoiseModel::Gaussian { sigma: 3.0 }, NoiseModel::Poisson { scale: 1.0 }] {
                let a = add_noise(&short, model, seed);
                let b = add_noise(&long, model, seed);
                prop_assert_eq!(a.as_f32().unwrap(), &b.as_f32().unwrap()[..w]);
            }
        }
    }
}
