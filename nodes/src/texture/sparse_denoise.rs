//! `texture.sparse_denoise`: image denoising by sparse coding of overlapping patches over an
//! overcomplete DCT dictionary or one learned by K-SVD (Elad & Aharon 2006).
//!
//! The pieces are plain functions: [`dct_dictionary`], [`omp`] (orthogonal matching pursuit),
//! [`ksvd`] (dictionary learning) and [`denoise_plane`].
//!
//! Determinism: patches are coded in parallel (each code is a sequential computation on its own
//! patch) in bands of a fixed number of patch rows, and the reconstructions are added to the
//! image in patch order; K-SVD's atom updates are sequential and its training patches are drawn
//! from one seeded generator. The result is bit-identical for any thread count.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Matrix, Metrics, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::Texture;
use crate::video::filters::SplitMix64;

/// Patch rows coded per parallel band (bounds the memory of pending reconstructions).
const BAND_PATCH_ROWS: usize = 16;

/// OMP stops when no atom correlates with the residual more than this (relative to ‖x‖).
const OMP_STALL: f64 = 1e-12;

param_enum! {
    /// Which dictionary codes the patches.
    pub enum DictionaryKind {
        /// Fixed overcomplete separable DCT.
        Dct = "dct",
        /// Learned by K-SVD on the noisy image's patches, starting from the DCT.
        Ksvd = "ksvd",
    }
}

params! {
    /// Parameters of `texture.sparse_denoise`.
    pub struct SparseDenoiseParams {
        /// Patch side, px (2..=16).
        patch_px: u32 = 8 => [min = 2, max = 16, unit = "px"],
        /// Step between coded patches, px (1..=patch_px; the last row and column of patches
        /// always touch the image's edge). 1 is the paper's setting; larger is faster.
        stride_px: u32 = 2 => [min = 1, unit = "px"],
        /// "dct" (fixed) or "ksvd" (learned on the noisy image).
        dictionary: DictionaryKind = DictionaryKind::Dct,
        /// Number of atoms: a perfect square k² with patch_px ≤ k ≤ 4·patch_px (k DCT
        /// frequencies per axis). The paper uses 256 for 8×8 patches.
        atoms: u32 = 256 => [min = 4],
        /// Most atoms per patch (≥ 1); coding stops earlier once the error target is met.
        max_atoms: u32 = 16 => [min = 1],
        /// Standard deviation of the noise, in the image's units (gray levels for u8), > 0.
        sigma: f64 = 20.0 => [above = 0.0],
        /// Error target gain C: a patch of n pixels is coded until ‖residual‖² ≤ n·(C·σ)²
        /// (> 0; the paper uses 1.15).
        gain: f64 = 1.15 => [above = 0.0],
        /// λ: weight of the noisy image in the final average, per pixel, against one per
        /// overlapping patch (≥ 0; the paper uses 30/σ for 0..255 images). 0 averages the
        /// patches only.
        noisy_weight: f64 = 0.0 => [min = 0.0],
        /// "ksvd": dictionary update sweeps (≥ 1).
        ksvd_iterations: u32 = 5 => [min = 1],
        /// "ksvd": most training patches, drawn at random from the coded patches (≥ 1).
        training_patches: u32 = 4000 => [min = 1],
        /// "ksvd": seed of the training-patch draw.
        seed: u64 = 0,
    }
}

/// Settings of [`denoise_plane`] (see [`SparseDenoiseParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DenoiseConfig {
    /// Patch side, px.
    pub patch_px: usize,
    /// Patch step, px.
    pub stride_px: usize,
    /// Dictionary kind.
    pub dictionary: DictionaryKind,
    /// DCT frequencies per axis (atoms = this squared).
    pub atoms_per_axis: usize,
    /// Most atoms per patch.
    pub max_atoms: usize,
    /// Noise standard deviation, image units.
    pub sigma: f64,
    /// Error target gain.
    pub gain: f64,
    /// λ.
    pub noisy_weight: f64,
    /// K-SVD sweeps.
    pub ksvd_iterations: usize,
    /// Most K-SVD training patches.
    pub training_patches: usize,
    /// K-SVD sampling seed.
    pub seed: u64,
}

/// Sparse-coding denoiser (`texture.sparse_denoise`). See [`denoise_plane`].
#[derive(Debug, Clone, PartialEq)]
pub struct SparseDenoise {
    config: DenoiseConfig,
}

impl Op for SparseDenoise {
    type Params = SparseDenoiseParams;
    const ID: &'static str = "texture.sparse_denoise";
    const SUMMARY: &'static str =
        "Removes Gaussian noise by sparse coding of overlapping patches (DCT or K-SVD dictionary).";
    const DOC: &'static str = r#"
Denoising by sparse and redundant representations of M. Elad and M. Aharon, "Image Denoising
Via Sparse and Redundant Representations Over Learned Dictionaries", IEEE TIP 15(12), 2006.

Every channel is processed alone. Patches of `patch_px` × `patch_px` (n pixels) are taken every
`stride_px` pixels (plus the last row and column, so all pixels are covered) and each is coded
by orthogonal matching pursuit (Pati, Rezaiifar & Krishnaprasad 1993): atoms are added greedily
(largest |⟨atom, residual⟩|, the coefficients refitted by least squares) until
‖residual‖² ≤ n·(`gain`·`sigma`)² or `max_atoms` atoms are used. The denoised image is

    x̂ = (λ·y + Σ_patches Rᵀ·D·α) / (λ + Σ_patches Rᵀ·1),

λ = `noisy_weight`, y the noisy image: every pixel is the average of the reconstructions of the
patches covering it, optionally blended with its noisy value. Integer images are rounded.

Dictionaries (`atoms` = k², k per axis): `"dct"` is the separable overcomplete DCT, atom
(u, v) = c_u ⊗ c_v with c_u[i] ∝ cos((2i + 1)·u·π / 2k), unit norm (for k = n it is the
orthonormal DCT-II basis of `filter.dct`). `"ksvd"` starts from it and runs
`ksvd_iterations` sweeps of K-SVD (Aharon, Elad & Bruckstein 2006) on at most
`training_patches` patches of the noisy channel, drawn with `seed`: sparse coding of all of
them, then, atom by atom, a rank-one update of the atom and its coefficients from the residual
of the patches that use it (one power-iteration step, the approximate K-SVD of Rubinstein,
Zibulevsky & Elad 2008); an unused atom is replaced by the worst-coded training patch.

Outputs `image` (the input's format), `dictionary` (a Matrix of channels·atoms rows and n
columns: row c·atoms + j is atom j of channel c, a patch in row-major order) and `metrics`:
`patches` coded per channel, `mean_atoms` per patch, `ksvd_rms` (the last sweep's training
representation RMS, image units; "ksvd" only).

Cost: patches × atoms × n per OMP step: `stride_px` and `atoms` trade speed for PSNR; K-SVD
adds about `ksvd_iterations` codings of the training set.

Example:
    "clean": (op: "texture.sparse_denoise", inputs: { "image": "noisy.image" },
              params: (sigma: 20.0, dictionary: "ksvd", atoms: 256, stride_px: 2)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Noisy image, any pixel format, at least patch_px on each side.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "image",
                PortType::Image,
                "Denoised image, the input's format.",
            ),
            PortSpec::new(
                "dictionary",
                PortType::Matrix,
                "(channels·atoms) × patch_px²: the atoms used, one per row.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "patches, mean_atoms, ksvd_rms (ksvd only).",
            ),
        ]
    }

    fn new(params: SparseDenoiseParams) -> Result<Self, String> {
        let SparseDenoiseParams {
            patch_px,
            stride_px,
            dictionary,
            atoms,
            max_atoms,
            sigma,
            gain,
            noisy_weight,
            ksvd_iterations,
            training_patches,
            seed,
        } = params;
        if !(2..=16).contains(&patch_px) {
            return Err(format!("`patch_px` must be in 2..=16, got {patch_px}"));
        }
        if stride_px == 0 || stride_px > patch_px {
            return Err(format!(
                "`stride_px` must be in 1..=patch_px ({patch_px}), got {stride_px}"
            ));
        }
        let per_axis = f64::from(atoms).sqrt().round() as u32;
        if per_axis * per_axis != atoms || per_axis < patch_px || per_axis > 4 * patch_px {
            return Err(format!(
                "`atoms` must be k² with patch_px ≤ k ≤ 4·patch_px ({}..={} for {patch_px} px patches), got {atoms}",
                patch_px * patch_px,
                16 * patch_px * patch_px
            ));
        }
        if max_atoms == 0 {
            return Err("`max_atoms` must be at least 1".into());
        }
        for (name, value) in [("sigma", sigma), ("gain", gain)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(format!("`{name}` must be positive and finite, got {value}"));
            }
        }
        if !(noisy_weight.is_finite() && noisy_weight >= 0.0) {
            return Err(format!(
                "`noisy_weight` must be finite and ≥ 0, got {noisy_weight}"
            ));
        }
        if ksvd_iterations == 0 || training_patches == 0 {
            return Err("`ksvd_iterations` and `training_patches` must be at least 1".into());
        }
        Ok(SparseDenoise {
            config: DenoiseConfig {
                patch_px: patch_px as usize,
                stride_px: stride_px as usize,
                dictionary,
                atoms_per_axis: per_axis as usize,
                max_atoms: max_atoms as usize,
                sigma,
                gain,
                noisy_weight,
                ksvd_iterations: ksvd_iterations as usize,
                training_patches: training_patches as usize,
                seed,
            },
        })
    }
}

impl Operator for SparseDenoise {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let noisy = Texture::from_image(image, "image")?;
        let p = self.config.patch_px;
        if noisy.width < p || noisy.height < p {
            return Err(OpError::input(
                "image",
                format!(
                    "is {}×{}, smaller than a {p} px patch",
                    noisy.width, noisy.height
                ),
            ));
        }
        let c = noisy.channels;
        let mut out = noisy.clone();
        let mut dictionary_rows = Vec::new();
        let (mut patches, mut atoms_used, mut ksvd_rms) = (0usize, 0usize, 0.0f64);
        for ch in 0..c {
            let plane: Vec<f64> = noisy
                .samples
                .iter()
                .skip(ch)
                .step_by(c)
                .map(|&s| f64::from(s))
                .collect();
            let result = denoise_plane(&plane, noisy.width, noisy.height, &self.config);
            for (o, &v) in out
                .samples
                .iter_mut()
                .skip(ch)
                .step_by(c)
                .zip(&result.plane)
            {
                *o = v as f32;
            }
            dictionary_rows.extend_from_slice(&result.dictionary.data);
            patches = result.patches;
            atoms_used += result.atoms_used;
            ksvd_rms += result.ksvd_rms.unwrap_or(0.0) / c as f64;
        }
        let dim = p * p;
        let dictionary = Matrix::new(dictionary_rows.len() / dim, dim, dictionary_rows)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let mut metrics = Metrics::new();
        metrics.insert("patches".into(), patches as f64);
        metrics.insert(
            "mean_atoms".into(),
            atoms_used as f64 / (patches * c).max(1) as f64,
        );
        if self.config.dictionary == DictionaryKind::Ksvd {
            metrics.insert("ksvd_rms".into(), ksvd_rms);
        }
        Ok(Outputs::new()
            .with("image", Value::image(out.to_image(image)?))
            .with("dictionary", Value::Matrix(Arc::new(dictionary)))
            .with("metrics", Value::metrics(metrics)))
    }
}

/// A dictionary of unit-norm atoms of `dim` samples, atom `j` at `data[j·dim..(j+1)·dim]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Dictionary {
    /// Samples per atom.
    pub dim: usize,
    /// Number of atoms.
    pub atoms: usize,
    /// The atoms, one after the other.
    pub data: Vec<f64>,
}

impl Dictionary {
    /// Atom `j`.
    pub fn atom(&self, j: usize) -> &[f64] {
        &self.data[j * self.dim..(j + 1) * self.dim]
    }
}

/// The separable overcomplete DCT dictionary for `patch_px × patch_px` patches with
/// `per_axis` frequencies per axis: atom u·per_axis + v is the outer product c_u ⊗ c_v (row
/// frequency u, column frequency v), c_u[i] ∝ cos((2i + 1)·u·π / (2·per_axis)), unit norm.
pub fn dct_dictionary(patch_px: usize, per_axis: usize) -> Dictionary {
    let one_d: Vec<Vec<f64>> = (0..per_axis)
        .map(|u| {
            let atom: Vec<f64> = (0..patch_px)
                .map(|i| {
                    ((2 * i + 1) as f64 * u as f64 * std::f64::consts::PI / (2 * per_axis) as f64)
                        .cos()
                })
                .collect();
            let norm = atom.iter().map(|v| v * v).sum::<f64>().sqrt();
            atom.iter().map(|v| v / norm).collect()
        })
        .collect();
    let dim = patch_px * patch_px;
    let mut data = Vec::with_capacity(per_axis * per_axis * dim);
    for cu in &one_d {
        for cv in &one_d {
            for a in cu {
                data.extend(cv.iter().map(|b| a * b));
            }
        }
    }
    Dictionary {
        dim,
        atoms: per_axis * per_axis,
        data,
    }
}

/// A sparse code: the atoms used, in the order chosen, and their coefficients.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SparseCode {
    /// Atom indices.
    pub atoms: Vec<usize>,
    /// Coefficients, one per atom.
    pub coefficients: Vec<f64>,
}

impl SparseCode {
    /// D·α, `dictionary.dim` samples.
    pub fn reconstruct(&self, dictionary: &Dictionary) -> Vec<f64> {
        let mut out = vec![0.0; dictionary.dim];
        for (&j, &a) in self.atoms.iter().zip(&self.coefficients) {
            for (o, d) in out.iter_mut().zip(dictionary.atom(j)) {
                *o += a * d;
            }
        }
        out
    }
}

/// Orthogonal matching pursuit: codes `signal` (`dictionary.dim` samples) with atoms added one
/// at a time — the one of largest |⟨atom, residual⟩| (lowest index on ties), then all
/// coefficients refitted by least squares — until ‖residual‖² ≤ `error_target` (a squared
/// norm), `max_atoms` atoms are used, or no atom reduces the residual.
pub fn omp(
    dictionary: &Dictionary,
    signal: &[f64],
    max_atoms: usize,
    error_target: f64,
) -> SparseCode {
    let dim = dictionary.dim;
    let norm2 = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>();
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut code = SparseCode::default();
    let mut residual = signal.to_vec();
    let stall = OMP_STALL * norm2(signal).sqrt();
    let limit = max_atoms.min(dim).min(dictionary.atoms);
    while norm2(&residual) > error_target && code.atoms.len() < limit {
        let mut best = None;
        let mut best_corr = stall;
        for j in 0..dictionary.atoms {
            let corr = dot(dictionary.atom(j), &residual).abs();
            if corr > best_corr && !code.atoms.contains(&j) {
                best_corr = corr;
                best = Some(j);
            }
        }
        let Some(j) = best else { break };
        code.atoms.push(j);
        let k = code.atoms.len();
        let gram = DMatrix::from_fn(k, k, |a, b| {
            dot(
                dictionary.atom(code.atoms[a]),
                dictionary.atom(code.atoms[b]),
            )
        });
        let rhs = DVector::from_fn(k, |a, _| dot(dictionary.atom(code.atoms[a]), signal));
        let Some(solution) = gram.cholesky().map(|ch| ch.solve(&rhs)) else {
            // The new atom is (numerically) dependent on the chosen ones: stop without it.
            code.atoms.pop();
            break;
        };
        code.coefficients = solution.iter().copied().collect();
        let approx = code.reconstruct(dictionary);
        for ((r, s), a) in residual.iter_mut().zip(signal).zip(&approx) {
            *r = s - a;
        }
    }
    code
}

/// The result of [`ksvd`].
#[derive(Debug, Clone, PartialEq)]
pub struct KsvdResult {
    /// The learned dictionary.
    pub dictionary: Dictionary,
    /// Representation RMS (per sample) of the training set before each sweep's atom updates,
    /// then after the last one: `iterations + 1` values.
    pub rms_history: Vec<f64>,
}

/// K-SVD (approximate rank-one updates): learns a dictionary for `training` (signals of
/// `initial.dim` samples, one after the other) from `initial`, coding with [`omp`]
/// (`max_atoms`, `error_target`) — see [`SparseDenoise`] for the method.
pub fn ksvd(
    training: &[f64],
    initial: &Dictionary,
    iterations: usize,
    max_atoms: usize,
    error_target: f64,
) -> KsvdResult {
    let dim = initial.dim;
    let signals: Vec<&[f64]> = training.chunks_exact(dim).collect();
    let mut dictionary = initial.clone();
    let code_all = |dictionary: &Dictionary| -> Vec<SparseCode> {
        signals
            .par_iter()
            .map(|s| omp(dictionary, s, max_atoms, error_target))
            .collect()
    };
    let residual_of = |dictionary: &Dictionary, code: &SparseCode, s: &[f64]| -> Vec<f64> {
        let approx = code.reconstruct(dictionary);
        s.iter().zip(&approx).map(|(a, b)| a - b).collect()
    };
    let rms = |dictionary: &Dictionary, codes: &[SparseCode]| -> f64 {
        let sum: f64 = signals
            .iter()
            .zip(codes)
            .map(|(s, c)| {
                residual_of(dictionary, c, s)
                    .iter()
                    .map(|v| v * v)
                    .sum::<f64>()
            })
            .sum();
        (sum / (signals.len() * dim).max(1) as f64).sqrt()
    };
    let mut history = Vec::with_capacity(iterations + 1);
    let mut codes = Vec::new();
    for _ in 0..iterations {
        codes = code_all(&dictionary);
        history.push(rms(&dictionary, &codes));
        // Candidates to replace unused atoms: the worst-coded signals, worst first.
        let mut worst: Vec<(f64, usize)> = signals
            .iter()
            .zip(&codes)
            .enumerate()
            .map(|(i, (s, c))| {
                (
                    residual_of(&dictionary, c, s).iter().map(|v| v * v).sum(),
                    i,
                )
            })
            .collect();
        worst.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut replacements = worst.into_iter().map(|(_, i)| i);
        for k in 0..dictionary.atoms {
            // The patches using atom k, and where in their code.
            let users: Vec<(usize, usize)> = codes
                .iter()
                .enumerate()
                .filter_map(|(i, c)| c.atoms.iter().position(|&a| a == k).map(|slot| (i, slot)))
                .collect();
            if users.is_empty() {
                if let Some(i) = replacements.next() {
                    let s = signals[i];
                    let norm = s.iter().map(|v| v * v).sum::<f64>().sqrt();
                    if norm > 0.0 {
                        for (d, v) in dictionary.data[k * dim..(k + 1) * dim].iter_mut().zip(s) {
                            *d = v / norm;
                        }
                    }
                }
                continue;
            }
            // Residuals without atom k's contribution: E = X_ω − Σ_{j≠k} d_j α_j.
            let errors: Vec<Vec<f64>> = users
                .iter()
                .map(|&(i, slot)| {
                    let mut e = residual_of(&dictionary, &codes[i], signals[i]);
                    let a = codes[i].coefficients[slot];
                    for (v, d) in e.iter_mut().zip(dictionary.atom(k)) {
                        *v += a * d;
                    }
                    e
                })
                .collect();
            // d = E·g / ‖E·g‖ with g the current coefficients; then g = Eᵀ·d.
            let mut atom = vec![0.0; dim];
            for (&(i, slot), e) in users.iter().zip(&errors) {
                let g = codes[i].coefficients[slot];
                for (d, v) in atom.iter_mut().zip(e) {
                    *d += g * v;
                }
            }
            let norm = atom.iter().map(|v| v * v).sum::<f64>().sqrt();
            if norm <= 0.0 {
                continue;
            }
            for d in &mut atom {
                *d /= norm;
            }
            for (&(i, slot), e) in users.iter().zip(&errors) {
                codes[i].coefficients[slot] = e.iter().zip(&atom).map(|(a, b)| a * b).sum();
            }
            dictionary.data[k * dim..(k + 1) * dim].copy_from_slice(&atom);
        }
    }
    history.push(rms(&dictionary, &codes));
    KsvdResult {
        dictionary,
        rms_history: history,
    }
}

/// The result of [`denoise_plane`].
#[derive(Debug, Clone, PartialEq)]
pub struct DenoisedPlane {
    /// The denoised plane.
    pub plane: Vec<f64>,
    /// The dictionary used.
    pub dictionary: Dictionary,
    /// Patches coded.
    pub patches: usize,
    /// Atoms used, summed over patches.
    pub atoms_used: usize,
    /// K-SVD's final training representation RMS ("ksvd" only).
    pub ksvd_rms: Option<f64>,
}

/// Patch corners along a side: every `stride` from 0, plus the last one (`len − patch`).
fn corners(len: usize, patch: usize, stride: usize) -> Vec<usize> {
    let last = len - patch;
    let mut out: Vec<usize> = (0..=last).step_by(stride).collect();
    if out.last() != Some(&last) {
        out.push(last);
    }
    out
}

/// Denoises one `width × height` plane (row-major, at least a patch on each side) as
/// described in [`SparseDenoise`].
pub fn denoise_plane(
    plane: &[f64],
    width: usize,
    height: usize,
    config: &DenoiseConfig,
) -> DenoisedPlane {
    let p = config.patch_px;
    let dim = p * p;
    let xs = corners(width, p, config.stride_px);
    let ys = corners(height, p, config.stride_px);
    let patch_at = |x: usize, y: usize| -> Vec<f64> {
        (0..p)
            .flat_map(|dy| plane[(y + dy) * width + x..][..p].iter().copied())
            .collect()
    };
    let error_target = dim as f64 * (config.gain * config.sigma).powi(2);
    let mut dictionary = dct_dictionary(p, config.atoms_per_axis);
    let mut ksvd_rms = None;
    if config.dictionary == DictionaryKind::Ksvd {
        let mut all: Vec<(usize, usize)> = ys
            .iter()
            .flat_map(|&y| xs.iter().map(move |&x| (x, y)))
            .collect();
        // Partial Fisher–Yates: the first `training_patches` positions of a seeded shuffle.
        let take = config.training_patches.min(all.len());
        let mut rng = SplitMix64::new(config.seed);
        for i in 0..take {
            let j = i + ((rng.uniform() * (all.len() - i) as f64) as usize).min(all.len() - i - 1);
            all.swap(i, j);
        }
        let training: Vec<f64> = all[..take]
            .iter()
            .flat_map(|&(x, y)| patch_at(x, y))
            .collect();
        let learned = ksvd(
            &training,
            &dictionary,
            config.ksvd_iterations,
            config.max_atoms,
            error_target,
        );
        ksvd_rms = learned.rms_history.last().copied();
        dictionary = learned.dictionary;
    }
    let mut sum = vec![0.0f64; width * height];
    let mut count = vec![0.0f64; width * height];
    let mut atoms_used = 0;
    for band in ys.chunks(BAND_PATCH_ROWS) {
        let coded: Vec<Vec<(Vec<f64>, usize)>> = band
            .par_iter()
            .map(|&y| {
                xs.iter()
                    .map(|&x| {
                        let code =
                            omp(&dictionary, &patch_at(x, y), config.max_atoms, error_target);
                        (code.reconstruct(&dictionary), code.atoms.len())
                    })
                    .collect()
            })
            .collect();
        for (&y, row) in band.iter().zip(coded) {
            for (&x, (patch, used)) in xs.iter().zip(row) {
                atoms_used += used;
                for dy in 0..p {
                    let base = (y + dy) * width + x;
                    for dx in 0..p {
                        sum[base + dx] += patch[dy * p + dx];
                        count[base + dx] += 1.0;
                    }
                }
            }
        }
    }
    let lambda = config.noisy_weight;
    let denoised = plane
        .iter()
        .zip(sum.iter().zip(&count))
        .map(|(&y, (&s, &n))| (lambda * y + s) / (lambda + n))
        .collect();
    DenoisedPlane {
        plane: denoised,
        dictionary,
        patches: xs.len() * ys.len(),
        atoms_used,
        ksvd_rms,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyze::quality::{error_stats, psnr_db};
    use crate::filter::frequency::dct::dct_matrix;
    use crate::filter::noise::{NoiseModel, add_noise};
    use ocellus_engine::value::{Channels, Image};

    fn random_dictionary(dim: usize, atoms: usize, seed: u64) -> Dictionary {
        let mut rng = SplitMix64::new(seed);
        let mut data: Vec<f64> = (0..dim * atoms).map(|_| rng.standard_normal()).collect();
        for atom in data.chunks_mut(dim) {
            let norm = atom.iter().map(|v| v * v).sum::<f64>().sqrt();
            atom.iter_mut().for_each(|v| *v /= norm);
        }
        Dictionary { dim, atoms, data }
    }

    /// A code of `k` atoms with coefficients of magnitude 1..3 and random signs.
    fn sparse_signal(
        dictionary: &Dictionary,
        k: usize,
        seed: u64,
    ) -> (Vec<usize>, Vec<f64>, Vec<f64>) {
        let mut rng = SplitMix64::new(seed);
        let mut atoms = Vec::new();
        while atoms.len() < k {
            let j = (rng.uniform() * dictionary.atoms as f64) as usize;
            if !atoms.contains(&j) {
                atoms.push(j);
            }
        }
        let coefficients: Vec<f64> = atoms
            .iter()
            .map(|_| (1.0 + 2.0 * rng.uniform()) * if rng.uniform() < 0.5 { -1.0 } else { 1.0 })
            .collect();
        let code = SparseCode {
            atoms: atoms.clone(),
            coefficients: coefficients.clone(),
        };
        let signal = code.reconstruct(dictionary);
        (atoms, coefficients, signal)
    }

    fn check_recovery(dictionary: &Dictionary, k: usize, seed: u64) {
        let (atoms, coefficients, signal) = sparse_signal(dictionary, k, seed);
        let code = omp(dictionary, &signal, 2 * k, 1e-20);
        let mut found: Vec<(usize, f64)> =
            code.atoms.iter().copied().zip(code.coefficients).collect();
        let mut truth: Vec<(usize, f64)> = atoms.into_iter().zip(coefficients).collect();
        found.sort_by_key(|a| a.0);
        truth.sort_by_key(|a| a.0);
        assert_eq!(
            found.len(),
            truth.len(),
            "seed {seed}: {found:?} vs {truth:?}"
        );
        for (f, t) in found.iter().zip(&truth) {
            assert_eq!(f.0, t.0, "seed {seed}");
            assert!((f.1 - t.1).abs() < 1e-9, "seed {seed}: {f:?} vs {t:?}");
        }
    }

    #[test]
    fn omp_recovers_exact_sparse_codes() {
        // Orthonormal basis (the complete DCT): any sparsity is recovered.
        let basis = dct_dictionary(8, 8);
        for seed in 0..10 {
            check_recovery(&basis, 6, seed);
        }
        // A random overcomplete dictionary (64 × 256): 3-sparse codes.
        let random = random_dictionary(64, 256, 42);
        for seed in 0..20 {
            check_recovery(&random, 3, seed);
        }
    }

    #[test]
    fn omp_stops_at_the_error_target_and_atom_budget() {
        let dictionary = random_dictionary(16, 40, 1);
        let mut rng = SplitMix64::new(3);
        let signal: Vec<f64> = (0..16).map(|_| rng.standard_normal()).collect();
        let code = omp(&dictionary, &signal, 3, 0.0);
        assert_eq!(code.atoms.len(), 3);
        let target = 0.5;
        let code = omp(&dictionary, &signal, 16, target);
        let approx = code.reconstruct(&dictionary);
        let residual: f64 = signal
            .iter()
            .zip(&approx)
            .map(|(a, b)| (a - b).powi(2))
            .sum();
        assert!(residual <= target);
        // One atom fewer would not have met it (OMP stops as soon as it can).
        let shorter = omp(&dictionary, &signal, code.atoms.len() - 1, 0.0);
        let approx = shorter.reconstruct(&dictionary);
        let residual: f64 = signal
            .iter()
            .zip(&approx)
            .map(|(a, b)| (a - b).powi(2))
            .sum();
        assert!(residual > target);
    }

    #[test]
    fn complete_dct_dictionary_is_the_dct_of_filter_dct() {
        let c = dct_matrix();
        let d = dct_dictionary(8, 8);
        for u in 0..8 {
            for v in 0..8 {
                let atom = d.atom(u * 8 + v);
                for i in 0..8 {
                    for j in 0..8 {
                        let expected = f64::from(c[u][i]) * f64::from(c[v][j]);
                        assert!((atom[i * 8 + j] - expected).abs() < 1e-6);
                    }
                }
            }
        }
        let over = dct_dictionary(6, 11);
        for j in 0..over.atoms {
            let norm: f64 = over.atom(j).iter().map(|v| v * v).sum();
            assert!((norm - 1.0).abs() < 1e-12);
        }
    }

    /// A 64×64 piecewise-smooth gray test image: a ramp, a bright disc and a striped square.
    fn clean_image() -> Image {
        let (w, h) = (64, 64);
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let mut v = 60.0 + 1.5 * x;
                if (x - 22.0).powi(2) + (y - 24.0).powi(2) < 144.0 {
                    v = 210.0;
                }
                if (36.0..58.0).contains(&x) && (36.0..58.0).contains(&y) {
                    v = if (x as usize / 4).is_multiple_of(2) {
                        40.0
                    } else {
                        170.0
                    };
                }
                v as u8
            })
            .collect();
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    fn config(dictionary: DictionaryKind) -> DenoiseConfig {
        DenoiseConfig {
            patch_px: 8,
            stride_px: 2,
            dictionary,
            atoms_per_axis: 11,
            max_atoms: 16,
            sigma: 20.0,
            gain: 1.15,
            noisy_weight: 0.0,
            ksvd_iterations: 3,
            training_patches: 600,
            seed: 1,
        }
    }

    fn denoise_image(noisy: &Image, config: &DenoiseConfig) -> Image {
        let plane: Vec<f64> = noisy
            .as_u8()
            .unwrap()
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        let result = denoise_plane(&plane, noisy.width(), noisy.height(), config);
        let data = result
            .plane
            .iter()
            .map(|v| v.round().clamp(0.0, 255.0) as u8)
            .collect();
        Image::from_u8(noisy.width(), noisy.height(), Channels::Gray, data).unwrap()
    }

    /// Denoising a known image with known noise (σ = 20) must gain more than 6 dB of PSNR with
    /// either dictionary (the measured gains are printed; see bench/notes/texture.md).
    #[test]
    fn denoising_raises_psnr() {
        let clean = clean_image();
        let noisy = add_noise(&clean, NoiseModel::Gaussian { sigma: 20.0 }, 9);
        let psnr = |img: &Image| psnr_db(error_stats(img, &clean).mse, 255.0).unwrap();
        let before = psnr(&noisy);
        for kind in [DictionaryKind::Dct, DictionaryKind::Ksvd] {
            let after = psnr(&denoise_image(&noisy, &config(kind)));
            eprintln!("{kind:?}: PSNR {before:.2} dB → {after:.2} dB");
            assert!(
                after > before + 6.0,
                "{kind:?}: {before:.2} → {after:.2} dB"
            );
        }
    }

    #[test]
    fn ksvd_lowers_the_representation_error() {
        let clean = clean_image();
        let noisy = add_noise(&clean, NoiseModel::Gaussian { sigma: 5.0 }, 2);
        let plane: Vec<f64> = noisy
            .as_u8()
            .unwrap()
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        let training: Vec<f64> = (0..50)
            .flat_map(|k| {
                let (x, y) = ((k * 7) % 56, (k * 11) % 56);
                let plane = &plane;
                (0..8).flat_map(move |dy| plane[(y + dy) * 64 + x..][..8].to_vec())
            })
            .collect();
        // Fixed sparsity (no error target): the error can only be compared at equal budgets.
        let result = ksvd(&training, &dct_dictionary(8, 10), 4, 3, 0.0);
        let history = &result.rms_history;
        assert_eq!(history.len(), 5);
        assert!(history[4] < 0.9 * history[0], "{history:?}");
    }

    #[test]
    fn same_result_for_one_and_many_threads() {
        let noisy = add_noise(&clean_image(), NoiseModel::Gaussian { sigma: 15.0 }, 4);
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| denoise_image(&noisy, &config(DictionaryKind::Ksvd)))
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn bad_params_are_rejected() {
        for params in [
            SparseDenoiseParams {
                atoms: 200,
                ..Default::default()
            },
            SparseDenoiseParams {
                atoms: 49,
                ..Default::default()
            },
            SparseDenoiseParams {
                stride_px: 9,
                ..Default::default()
            },
            SparseDenoiseParams {
                sigma: f64::NAN,
                ..Default::default()
            },
            SparseDenoiseParams {
                noisy_weight: -1.0,
                ..Default::default()
            },
        ] {
            assert!(SparseDenoise::new(params).is_err());
        }
    }
}
