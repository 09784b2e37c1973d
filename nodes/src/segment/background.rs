//! `segment.background`: background subtraction over an image sequence — running average,
//! per-pixel Gaussian, or Stauffer–Grimson mixture of Gaussians.
//!
//! The per-frame step is [`BackgroundSubtractor::apply`]: it keeps the background model between
//! calls, so a streaming caller feeds frames one at a time; [`Background`] (the operator) loops
//! it over a list of frames.
//!
//! # Numerics
//!
//! Every method works on samples converted to f32 on a 0–255 scale whatever the input depth
//! ([`to_levels`]: u8 as is, u16 divided by 257, f32 multiplied by 255), so thresholds and
//! variances are in 8-bit gray levels for every format. Pixels are independent: the model is
//! updated in fixed-size pixel bands in parallel, each pixel by the same arithmetic whatever the
//! thread, so masks and background are bit-identical for any thread count.

use ocellus_engine::op::{
    Inputs, Op, OpError, Operator, Outputs, Packet, PortSpec, RunContext, SequenceState,
    run_sequence_batch,
};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Depth, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

/// Pixels per parallel band (a constant, never derived from the thread count).
const BAND_PIXELS: usize = 8192;

/// Smallest variance a Gaussian may shrink to, gray levels² (σ ≥ 2 levels): keeps a perfectly
/// still background from turning every tiny change into foreground.
pub const MIN_VARIANCE: f32 = 4.0;

/// Most mixture components per pixel.
pub const MAX_GAUSSIANS: u32 = 8;

param_enum! {
    /// Background model of `segment.background`.
    pub enum BackgroundMethod {
        /// Running average `B ← (1−α)·B + α·I`; foreground where `max_c |I − B| > threshold`.
        RunningAverage = "running_average",
        /// Per-pixel, per-channel running mean and variance; foreground where the normalized
        /// distance `Σ_c (I−μ)²/σ²` exceeds `channels · k_sigma²`.
        Gaussian = "gaussian",
        /// Stauffer–Grimson mixture of `n_gaussians` Gaussians per pixel.
        Mog = "mog",
    }
}

params! {
    /// Parameters of `segment.background`.
    pub struct BackgroundParams {
        /// Background model.
        method: BackgroundMethod = BackgroundMethod::Mog,
        /// Learning rate α in (0, 1] (dimensionless): the weight of each new frame in the
        /// model. Frame n (1-based) uses max(α, 1/n), so the first frames build a plain mean.
        learning_rate: f64 = 0.01,
        /// `running_average`: foreground threshold on |I − B|, gray levels (0–255 scale).
        threshold: f64 = 30.0,
        /// `gaussian` and `mog`: match / foreground distance in standard deviations
        /// (dimensionless).
        k_sigma: f64 = 2.5,
        /// `mog`: Gaussians per pixel, 1..=8.
        n_gaussians: u32 = 3,
        /// `mog`: fraction T in (0, 1] of the total weight explained by the background: the
        /// background is the first Gaussians by weight/σ whose cumulative weight exceeds T.
        background_ratio: f64 = 0.7,
        /// `gaussian` and `mog`: variance of a new Gaussian, gray levels² (0–255 scale); 225
        /// is σ = 15 levels.
        initial_variance: f64 = 225.0,
    }
}

/// Settings of a [`BackgroundSubtractor`] (checked by [`BackgroundConfig::check`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BackgroundConfig {
    /// Background model.
    pub method: BackgroundMethod,
    /// Learning rate α in (0, 1].
    pub learning_rate: f32,
    /// Running-average threshold, gray levels.
    pub threshold: f32,
    /// Distance in standard deviations.
    pub k_sigma: f32,
    /// Gaussians per pixel (`mog`).
    pub n_gaussians: usize,
    /// Background weight fraction T (`mog`).
    pub background_ratio: f32,
    /// Variance of a new Gaussian, gray levels².
    pub initial_variance: f32,
}

impl Default for BackgroundConfig {
    fn default() -> Self {
        BackgroundConfig {
            method: BackgroundMethod::Mog,
            learning_rate: 0.01,
            threshold: 30.0,
            k_sigma: 2.5,
            n_gaussians: 3,
            background_ratio: 0.7,
            initial_variance: 225.0,
        }
    }
}

impl BackgroundConfig {
    /// An error naming the first parameter out of range.
    pub fn check(&self) -> Result<(), String> {
        let finite_pos = |v: f32| v.is_finite() && v > 0.0;
        if !(finite_pos(self.learning_rate) && self.learning_rate <= 1.0) {
            return Err(format!(
                "`learning_rate` must be in (0, 1], got {}",
                self.learning_rate
            ));
        }
        if !(self.threshold.is_finite() && self.threshold >= 0.0) {
            return Err(format!(
                "`threshold` must be a finite number ≥ 0 gray levels, got {}",
                self.threshold
            ));
        }
        if !finite_pos(self.k_sigma) {
            return Err(format!(
                "`k_sigma` must be a positive finite number, got {}",
                self.k_sigma
            ));
        }
        if !(1..=MAX_GAUSSIANS as usize).contains(&self.n_gaussians) {
            return Err(format!(
                "`n_gaussians` must be between 1 and {MAX_GAUSSIANS}, got {}",
                self.n_gaussians
            ));
        }
        if !(finite_pos(self.background_ratio) && self.background_ratio <= 1.0) {
            return Err(format!(
                "`background_ratio` must be in (0, 1], got {}",
                self.background_ratio
            ));
        }
        if !(self.initial_variance.is_finite() && self.initial_variance >= MIN_VARIANCE) {
            return Err(format!(
                "`initial_variance` must be a finite number ≥ {MIN_VARIANCE} gray levels², got {}",
                self.initial_variance
            ));
        }
        Ok(())
    }
}

/// Background subtraction (`segment.background`). See [`BackgroundSubtractor`].
#[derive(Debug, Clone, PartialEq)]
pub struct Background {
    config: BackgroundConfig,
}

impl Op for Background {
    type Params = BackgroundParams;
    const ID: &'static str = "segment.background";
    const SUMMARY: &'static str =
        "Separates moving foreground from a learned background over a sequence of frames.";
    const DOC: &'static str = r#"
Learns a per-pixel background model from a list of frames (in order) and marks, in each frame,
the pixels that do not fit it. Outputs one u8 gray mask per frame (255 = foreground, 0 =
background) and the final background model as an image in the frames' format.

All frames must share size, channels (gray, RGB or RGBA; all channels are used) and depth
(u8, u16, f32). Samples are put on a 0–255 scale first (u16 / 257, f32 × 255), so `threshold`
and `initial_variance` are in 8-bit gray levels for every depth. Frame n (1-based) updates the
model with rate α_n = max(`learning_rate`, 1/n), so the model starts as a plain running mean of
the first frames (OpenCV uses 1/min(n, history) in the same way). The first frame's mask is all
background.

Methods (`method`):
- `running_average`: B ← (1−α)·B + α·I for every pixel; foreground where max over channels of
  |I − B| > `threshold` (tested before the update).
- `gaussian` (Wren et al., "Pfinder", 1997): per pixel and channel a running mean μ and
  variance σ², starting at the first frame and `initial_variance`; foreground where
  Σ_c (I−μ_c)²/σ_c² > C·`k_sigma`² (C channels: the root-mean-square z-score exceeds k, so
  k means the same for gray and colour); background pixels then learn (selective update, so a
  passing object does not inflate the variance): μ ← μ + α·d, σ² ← (1−α)·(σ² + α·d²) with
  d = I − μ (the exponentially weighted variance), σ² ≥ 4. An object that stops stays
  foreground under this method; `mog` absorbs it as its Gaussian gains weight.
- `mog` (Stauffer & Grimson, "Adaptive background mixture models for real-time tracking",
  CVPR 1999): per pixel up to `n_gaussians` Gaussians (weight w, mean μ, one variance σ² shared
  by the channels), kept sorted by w/σ. The first one with Σ_c (I−μ_c)² < C·`k_sigma`²·σ²
  matches (the Mahalanobis test of an isotropic covariance, normalized by the C channels); weights become (1−α)·w + α·[matched], the
  matched Gaussian moves with ρ = α/w: μ ← (1−ρ)μ + ρI, σ² ← (1−ρ)σ² + ρ·|I−μ|²/channels
  (σ² ≥ 4). Without a match the weakest Gaussian is replaced by one at I with variance
  `initial_variance` and weight α, and the weights are renormalized. The background is the
  first B Gaussians (by w/σ) whose cumulative weight exceeds `background_ratio`; a pixel is
  foreground when it matched none of them. The background output is the weight-averaged mean of
  those B Gaussians.

Differences from OpenCV: `cv::bgsegm::BackgroundSubtractorMOG` (KaewTraKulPong & Bowden) uses
the same match/update structure but a fixed initial weight and its own warm-up; MOG2 adapts the
number of Gaussians and marks shadows. No shadow detection here.

In a stream the model is the node's state: each frame is classified and learned as it
arrives (`masks`, `scores` per frame), `background` is the model after the last frame —
the same values as a batch run over the list.

Example:
    "fg": (op: "segment.background", inputs: { "frames": "clip.frames" }, params: (method: "mog", learning_rate: 0.01)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "frames",
            PortType::Image.list_of(),
            "Frames in time order, all of one size and pixel format (gray/RGB/RGBA, u8/u16/f32).",
        )
        .per_frame()]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "masks",
                PortType::Image.list_of(),
                "One u8 gray mask per frame: 255 foreground, 0 background.",
            )
            .per_frame(),
            PortSpec::new(
                "background",
                PortType::Image,
                "The background model after the last frame, in the frames' pixel format.",
            ),
            PortSpec::new(
                "scores",
                PortType::Image.list_of(),
                "One gray f32 image per frame: the RMS over channels of |frame − background| in \
                 8-bit gray levels, against the background before the frame's update (0 for the \
                 first frame). A graded foreground score for ROC sweeps (`analyze.roc`).",
            )
            .per_frame(),
        ]
    }

    fn new(params: BackgroundParams) -> Result<Self, String> {
        let BackgroundParams {
            method,
            learning_rate,
            threshold,
            k_sigma,
            n_gaussians,
            background_ratio,
            initial_variance,
        } = params;
        let config = BackgroundConfig {
            method,
            learning_rate: learning_rate as f32,
            threshold: threshold as f32,
            k_sigma: k_sigma as f32,
            n_gaussians: n_gaussians as usize,
            background_ratio: background_ratio as f32,
            initial_variance: initial_variance as f32,
        };
        config.check()?;
        Ok(Background { config })
    }
}

impl Operator for Background {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_sequence_batch(self, ctx, inputs, &Self::outputs())
    }

    fn sequence(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        Some(
            BackgroundSubtractor::new(self.config)
                .map(|s| Box::new(BackgroundState(s)) as Box<dyn SequenceState>)
                .map_err(|e| OpError::failed(format!("background model: {e}"))),
        )
    }
}

/// `segment.background` between frames: the model.
struct BackgroundState(BackgroundSubtractor);

impl SequenceState for BackgroundState {
    fn push(
        &mut self,
        _ctx: &RunContext,
        _packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        let frame = inputs.image("frames")?;
        let subtractor = &mut self.0;
        let score = match subtractor.background() {
            Some(Ok(background)) if background.channels() == frame.channels() => {
                background_distance(frame, &background)
            }
            Some(Err(e)) => return Err(OpError::failed(format!("background image: {e}"))),
            _ => Image::from_f32(
                frame.width(),
                frame.height(),
                Channels::Gray,
                vec![0.0; frame.width() * frame.height()],
            )
            .map_err(|e| e.to_string()),
        }
        .map_err(|e| OpError::failed(format!("score image: {e}")))?;
        let mask = subtractor
            .apply(frame)
            .map_err(|e| OpError::input("frames", e))?;
        Ok(Outputs::new()
            .with("masks", Value::image(mask))
            .with("scores", Value::image(score)))
    }

    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        let background = match self.0.background() {
            Some(b) => b.map_err(|e| OpError::failed(format!("background image: {e}")))?,
            None => return Err(OpError::input("frames", "needs at least one frame")),
        };
        Ok(Outputs::new().with("background", Value::image(background)))
    }
}

/// Per pixel, the RMS over channels of `|frame − background|` in 0–255 levels (gray f32).
/// Errors if the two differ in size or channels.
pub fn background_distance(frame: &Image, background: &Image) -> Result<Image, String> {
    if (frame.width(), frame.height(), frame.channels())
        != (
            background.width(),
            background.height(),
            background.channels(),
        )
    {
        return Err("frame and background differ in size or channels".into());
    }
    let c = frame.channels().count();
    let (x, b) = (to_levels(frame), to_levels(background));
    let score = x
        .chunks_exact(c)
        .zip(b.chunks_exact(c))
        .map(|(x, b)| {
            let sum: f32 = x.iter().zip(b).map(|(x, b)| (x - b) * (x - b)).sum();
            (sum / c as f32).sqrt()
        })
        .collect();
    Image::from_f32(frame.width(), frame.height(), Channels::Gray, score).map_err(|e| e.to_string())
}

/// Samples of `image` as f32 on a 0–255 scale: u8 as is, u16 / 257, f32 × 255.
pub fn to_levels(image: &Image) -> Vec<f32> {
    match image.data() {
        PixelData::U8(v) => v.iter().map(|&s| f32::from(s)).collect(),
        PixelData::U16(v) => v.iter().map(|&s| f32::from(s) * (1.0 / 257.0)).collect(),
        PixelData::F32(v) => v.iter().map(|&s| s * 255.0).collect(),
    }
}

/// Converts 0–255-scale levels back to `depth` (rounded and saturated for integers).
pub fn from_levels(levels: &[f32], depth: Depth) -> PixelData {
    match depth {
        Depth::U8 => PixelData::U8(
            levels
                .iter()
                .map(|&l| l.round_ties_even().clamp(0.0, 255.0) as u8)
                .collect(),
        ),
        Depth::U16 => PixelData::U16(
            levels
                .iter()
                .map(|&l| (l * 257.0).round_ties_even().clamp(0.0, 65535.0) as u16)
                .collect(),
        ),
        Depth::F32 => PixelData::F32(levels.iter().map(|&l| l * (1.0 / 255.0)).collect()),
    }
}

/// The model state, per pixel.
#[derive(Debug, Clone)]
enum Model {
    /// Background per sample.
    Average { mean: Vec<f32> },
    /// Mean and variance per sample.
    Gaussian { mean: Vec<f32>, var: Vec<f32> },
    /// Per pixel `k` components of `[weight, variance, mean_0 .. mean_{c−1}]`, sorted by w/σ.
    Mog { comps: Vec<f32> },
}

/// A background model that learns frame by frame: [`apply`](Self::apply) classifies a frame
/// and updates the model. The first frame fixes the size and pixel format.
#[derive(Debug, Clone)]
pub struct BackgroundSubtractor {
    config: BackgroundConfig,
    width: usize,
    height: usize,
    channels: Channels,
    depth: Depth,
    frames: u64,
    model: Option<Model>,
}

impl BackgroundSubtractor {
    /// An empty model; errors if `config` is out of range.
    pub fn new(config: BackgroundConfig) -> Result<Self, String> {
        config.check()?;
        Ok(BackgroundSubtractor {
            config,
            width: 0,
            height: 0,
            channels: Channels::Gray,
            depth: Depth::U8,
            frames: 0,
            model: None,
        })
    }

    /// Frames seen so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Classifies `frame` (u8 gray mask, 255 = foreground) and learns from it. Errors if the
    /// frame's size or format differs from the first frame's.
    pub fn apply(&mut self, frame: &Image) -> Result<Image, String> {
        let c = frame.channels().count();
        let n = frame.width() * frame.height();
        let levels = to_levels(frame);
        if levels.iter().any(|s| !s.is_finite()) {
            return Err("contains NaN or infinite samples".into());
        }
        let mut mask = vec![0u8; n];
        let Some(model) = self.model.as_mut() else {
            self.width = frame.width();
            self.height = frame.height();
            self.channels = frame.channels();
            self.depth = frame.depth();
            self.frames = 1;
            self.model = Some(initial_model(&self.config, &levels, c));
            return Image::from_u8(self.width, self.height, Channels::Gray, mask)
                .map_err(|e| e.to_string());
        };
        if (
            frame.width(),
            frame.height(),
            frame.channels(),
            frame.depth(),
        ) != (self.width, self.height, self.channels, self.depth)
        {
            return Err(format!(
                "is {}×{} {} {}, but the first frame was {}×{} {} {}",
                frame.width(),
                frame.height(),
                frame.channels().name(),
                frame.depth().name(),
                self.width,
                self.height,
                self.channels.name(),
                self.depth.name()
            ));
        }
        self.frames += 1;
        let alpha = self.config.learning_rate.max(1.0 / self.frames as f32);
        let cfg = &self.config;
        match model {
            Model::Average { mean } => {
                let t = cfg.threshold;
                mean.par_chunks_mut(BAND_PIXELS * c)
                    .zip(levels.par_chunks(BAND_PIXELS * c))
                    .zip(mask.par_chunks_mut(BAND_PIXELS))
                    .for_each(|((b, x), m)| average_step(b, x, m, c, alpha, t));
            }
            Model::Gaussian { mean, var } => {
                // RMS over channels of the z-scores: Σ_c d²/σ² against c·k².
                let k2 = cfg.k_sigma * cfg.k_sigma * c as f32;
                mean.par_chunks_mut(BAND_PIXELS * c)
                    .zip(var.par_chunks_mut(BAND_PIXELS * c))
                    .zip(levels.par_chunks(BAND_PIXELS * c))
                    .zip(mask.par_chunks_mut(BAND_PIXELS))
                    .for_each(|(((mu, v), x), m)| gaussian_step(mu, v, x, m, c, alpha, k2));
            }
            Model::Mog { comps } => {
                let stride = cfg.n_gaussians * (c + 2);
                let band: MogBand = match c {
                    1 => mog_band::<1>,
                    2 => mog_band::<2>,
                    3 => mog_band::<3>,
                    _ => mog_band::<4>,
                };
                comps
                    .par_chunks_mut(BAND_PIXELS * stride)
                    .zip(levels.par_chunks(BAND_PIXELS * c))
                    .zip(mask.par_chunks_mut(BAND_PIXELS))
                    .for_each(|((g, x), m)| band(g, x, m, cfg, alpha));
            }
        }
        Image::from_u8(self.width, self.height, Channels::Gray, mask).map_err(|e| e.to_string())
    }

    /// The current background image in the first frame's format, or `None` before any frame.
    pub fn background(&self) -> Option<Result<Image, String>> {
        let model = self.model.as_ref()?;
        let c = self.channels.count();
        let levels = match model {
            Model::Average { mean } | Model::Gaussian { mean, .. } => mean.clone(),
            Model::Mog { comps } => {
                let stride = self.config.n_gaussians * (c + 2);
                let mut out = Vec::with_capacity(self.width * self.height * c);
                for g in comps.chunks_exact(stride) {
                    mog_background(g, c, self.config.background_ratio, &mut out);
                }
                out
            }
        };
        Some(
            Image::new(
                self.width,
                self.height,
                self.channels,
                from_levels(&levels, self.depth),
            )
            .map_err(|e| e.to_string()),
        )
    }
}

fn initial_model(cfg: &BackgroundConfig, levels: &[f32], c: usize) -> Model {
    match cfg.method {
        BackgroundMethod::RunningAverage => Model::Average {
            mean: levels.to_vec(),
        },
        BackgroundMethod::Gaussian => Model::Gaussian {
            mean: levels.to_vec(),
            var: vec![cfg.initial_variance; levels.len()],
        },
        BackgroundMethod::Mog => {
            let k = cfg.n_gaussians;
            let stride = k * (c + 2);
            let mut comps = vec![0.0f32; levels.len() / c.max(1) * stride];
            for (g, x) in comps.chunks_exact_mut(stride).zip(levels.chunks_exact(c)) {
                for comp in g.chunks_exact_mut(c + 2) {
                    comp[1] = cfg.initial_variance;
                }
                g[0] = 1.0;
                g[2..2 + c].copy_from_slice(x);
            }
            Model::Mog { comps }
        }
    }
}

fn average_step(b: &mut [f32], x: &[f32], m: &mut [u8], c: usize, alpha: f32, t: f32) {
    for ((b, x), m) in b.chunks_exact_mut(c).zip(x.chunks_exact(c)).zip(m) {
        let mut diff = 0.0f32;
        for (b, &x) in b.iter_mut().zip(x) {
            diff = diff.max((x - *b).abs());
            *b += alpha * (x - *b);
        }
        *m = if diff > t { 255 } else { 0 };
    }
}

fn gaussian_step(
    mu: &mut [f32],
    v: &mut [f32],
    x: &[f32],
    m: &mut [u8],
    c: usize,
    alpha: f32,
    k2: f32,
) {
    for (((mu, v), x), m) in mu
        .chunks_exact_mut(c)
        .zip(v.chunks_exact_mut(c))
        .zip(x.chunks_exact(c))
        .zip(m)
    {
        let mut dist = 0.0f32;
        for ((mu, v), &x) in mu.iter().zip(v.iter()).zip(x) {
            let d = x - *mu;
            dist += d * d / *v;
        }
        if dist > k2 {
            *m = 255;
            continue;
        }
        *m = 0;
        for ((mu, v), &x) in mu.iter_mut().zip(v.iter_mut()).zip(x) {
            let d = x - *mu;
            *mu += alpha * d;
            *v = ((1.0 - alpha) * (*v + alpha * d * d)).max(MIN_VARIANCE);
        }
    }
}

/// A band of mixture pixels: components, samples, mask, settings, learning rate.
type MogBand = fn(&mut [f32], &[f32], &mut [u8], &BackgroundConfig, f32);

/// [`mog_pixel`] over a band of pixels with `C` channels.
fn mog_band<const C: usize>(
    g: &mut [f32],
    x: &[f32],
    m: &mut [u8],
    cfg: &BackgroundConfig,
    alpha: f32,
) {
    let stride = cfg.n_gaussians * (C + 2);
    for ((g, x), m) in g.chunks_exact_mut(stride).zip(x.as_chunks::<C>().0).zip(m) {
        *m = mog_pixel::<C>(g, x, cfg, alpha);
    }
}

/// One pixel of the mixture: `g` holds `k` components `[w, σ², μ_0..μ_{C−1}]` sorted by w/σ.
/// Returns the mask value.
fn mog_pixel<const C: usize>(
    g: &mut [f32],
    x: &[f32; C],
    cfg: &BackgroundConfig,
    alpha: f32,
) -> u8 {
    let c = C;
    let s = c + 2;
    let k = g.len() / s;
    // σ² is a per-channel variance: Σ_c d² is compared with c·k²·σ².
    let k2 = cfg.k_sigma * cfg.k_sigma * c as f32;
    let mut matched = None;
    for (i, comp) in g.chunks_exact(s).enumerate() {
        if comp[0] <= 0.0 {
            break;
        }
        let d2: f32 = comp[2..]
            .iter()
            .zip(x)
            .map(|(&m, &x)| (x - m) * (x - m))
            .sum();
        if d2 < k2 * comp[1] {
            matched = Some(i);
            break;
        }
    }
    let mut total = 0.0f32;
    for comp in g.chunks_exact_mut(s) {
        comp[0] *= 1.0 - alpha;
    }
    let pos = match matched {
        Some(i) => {
            let comp = &mut g[i * s..(i + 1) * s];
            comp[0] += alpha;
            let rho = (alpha / comp[0]).min(1.0);
            let mut d2 = 0.0f32;
            for (m, &x) in comp[2..].iter_mut().zip(x) {
                *m += rho * (x - *m);
                d2 += (x - *m) * (x - *m);
            }
            comp[1] = ((1.0 - rho) * comp[1] + rho * d2 / c as f32).max(MIN_VARIANCE);
            i
        }
        None => {
            let comp = &mut g[(k - 1) * s..];
            comp[0] = alpha;
            comp[1] = cfg.initial_variance;
            comp[2..].copy_from_slice(x);
            k - 1
        }
    };
    for comp in g.chunks_exact(s) {
        total += comp[0];
    }
    if total > 0.0 {
        let inv = 1.0 / total;
        for comp in g.chunks_exact_mut(s) {
            comp[0] *= inv;
        }
    }
    // Only the changed component can be out of order: bubble it into place. w_a/σ_a > w_b/σ_b
    // is tested as w_a²·σ_b² > w_b²·σ_a² (weights ≥ 0, variances > 0).
    let before = |g: &[f32], a: usize, b: usize| {
        let (wa, va, wb, vb) = (g[a * s], g[a * s + 1], g[b * s], g[b * s + 1]);
        wa * wa * vb > wb * wb * va
    };
    let mut pos = pos;
    while pos > 0 && before(g, pos, pos - 1) {
        swap_comps(g, pos, pos - 1, s);
        pos -= 1;
    }
    while pos + 1 < k && before(g, pos + 1, pos) {
        swap_comps(g, pos, pos + 1, s);
        pos += 1;
    }
    if matched.is_none() {
        return 255;
    }
    // Background: the first B components whose cumulative weight exceeds T.
    let mut cum = 0.0f32;
    for i in 0..k {
        if i == pos {
            return 0;
        }
        cum += g[i * s];
        if cum > cfg.background_ratio {
            break;
        }
    }
    255
}

fn swap_comps(g: &mut [f32], a: usize, b: usize, s: usize) {
    for j in 0..s {
        g.swap(a * s + j, b * s + j);
    }
}

/// Appends the weight-averaged mean of the background components of one pixel to `out`.
fn mog_background(g: &[f32], c: usize, ratio: f32, out: &mut Vec<f32>) {
    let s = c + 2;
    let mut acc = [0.0f32; 4];
    let mut wsum = 0.0f32;
    for comp in g.chunks_exact(s) {
        if comp[0] <= 0.0 {
            break;
        }
        wsum += comp[0];
        for (a, &m) in acc.iter_mut().zip(&comp[2..]) {
            *a += comp[0] * m;
        }
        if wsum > ratio {
            break;
        }
    }
    let inv = if wsum > 0.0 { 1.0 / wsum } else { 0.0 };
    out.extend(acc[..c].iter().map(|a| a * inv));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use ocellus_engine::params::{ParamValue, Params};

    /// A moving-square sequence: a static textured background (levels 60..=120) with
    /// per-frame uniform noise in ±`noise`, empty for `warmup` frames, then a `side`-px
    /// square of level `fg` moving 2 px right and 1 px down per frame. Returns the frames (as
    /// 0–255 levels, `c` channels) and the true masks.
    fn sequence(
        w: usize,
        h: usize,
        c: usize,
        frames: usize,
        warmup: usize,
        noise: f64,
    ) -> (Vec<Vec<f32>>, Vec<Vec<bool>>) {
        let texture = randoms(7, w * h * c);
        let side = 10;
        let mut out = Vec::new();
        let mut truth = Vec::new();
        for f in 0..frames {
            let jitter = randoms(100 + f as u64, w * h * c);
            let mut img: Vec<f32> = texture
                .iter()
                .zip(&jitter)
                .map(|(t, j)| (60.0 + 60.0 * t + noise * (2.0 * j - 1.0)) as f32)
                .collect();
            let mut mask = vec![false; w * h];
            if f >= warmup {
                let t = f - warmup;
                let (x0, y0) = (2 + 2 * t, 3 + t);
                for y in y0..(y0 + side).min(h) {
                    for x in x0..(x0 + side).min(w) {
                        mask[y * w + x] = true;
                        for ch in 0..c {
                            img[(y * w + x) * c + ch] = [220.0, 30.0, 200.0][ch % 3];
                        }
                    }
                }
            }
            out.push(img);
            truth.push(mask);
        }
        (out, truth)
    }

    fn to_image(levels: &[f32], w: usize, h: usize, c: usize, depth: Depth) -> Image {
        let channels = [
            Channels::Gray,
            Channels::Gray,
            Channels::Gray,
            Channels::Rgb,
        ][c];
        Image::new(w, h, channels, from_levels(levels, depth)).unwrap()
    }

    fn precision_recall(config: BackgroundConfig, c: usize, depth: Depth) -> (f64, f64) {
        let (w, h) = (64, 48);
        // Long enough that the warm-up rate 1/n has come down to about α.
        let warmup = 100;
        let (frames, truth) = sequence(w, h, c, warmup + 20, warmup, 6.0);
        let mut sub = BackgroundSubtractor::new(config).unwrap();
        let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
        for (k, (f, t)) in frames.iter().zip(&truth).enumerate() {
            let mask = sub.apply(&to_image(f, w, h, c, depth)).unwrap();
            let m = mask.as_u8().unwrap();
            assert!(m.iter().all(|&v| v == 0 || v == 255));
            if k < warmup {
                continue;
            }
            for (&m, &t) in m.iter().zip(t) {
                match (m == 255, t) {
                    (true, true) => tp += 1,
                    (true, false) => fp += 1,
                    (false, true) => fneg += 1,
                    _ => {}
                }
            }
        }
        (tp as f64 / (tp + fp) as f64, tp as f64 / (tp + fneg) as f64)
    }

    #[test]
    fn moving_square_is_found_by_every_method() {
        for method in BackgroundMethod::ALL {
            for c in [1, 3] {
                for depth in [Depth::U8, Depth::F32, Depth::U16] {
                    let config = BackgroundConfig {
                        method: *method,
                        ..BackgroundConfig::default()
                    };
                    let (p, r) = precision_recall(config, c, depth);
                    assert!(
                        p > 0.95 && r > 0.95,
                        "{} c={c} {depth:?}: precision {p:.4} recall {r:.4}",
                        method.name()
                    );
                }
            }
        }
    }

    #[test]
    fn background_converges_to_the_static_scene() {
        let (w, h, c) = (32, 24, 3);
        let (frames, _) = sequence(w, h, c, 40, 40, 0.0);
        for method in BackgroundMethod::ALL {
            let config = BackgroundConfig {
                method: *method,
                ..BackgroundConfig::default()
            };
            let mut sub = BackgroundSubtractor::new(config).unwrap();
            for f in &frames {
                sub.apply(&to_image(f, w, h, c, Depth::F32)).unwrap();
            }
            let bg = sub.background().unwrap().unwrap();
            let levels = to_levels(&bg);
            let err = levels
                .iter()
                .zip(&frames[0])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(err < 1e-3, "{}: {err}", method.name());
        }
    }

    #[test]
    fn running_average_hand_computed() {
        let config = BackgroundConfig {
            method: BackgroundMethod::RunningAverage,
            learning_rate: 0.25,
            threshold: 10.0,
            ..BackgroundConfig::default()
        };
        let mut sub = BackgroundSubtractor::new(config).unwrap();
        let img = |v: Vec<u8>| Image::from_u8(2, 1, Channels::Gray, v).unwrap();
        assert_eq!(
            sub.apply(&img(vec![100, 100])).unwrap().as_u8().unwrap(),
            [0, 0]
        );
        // Frame 2: α = max(0.25, 1/2) = 0.5; |108 − 100| = 8 ≤ 10, |120 − 100| = 20 > 10.
        assert_eq!(
            sub.apply(&img(vec![108, 120])).unwrap().as_u8().unwrap(),
            [0, 255]
        );
        // B = (104, 110).
        let bg = sub.background().unwrap().unwrap();
        assert_eq!(bg.as_u8().unwrap(), [104, 110]);
        // Frame 3: α = max(0.25, 1/3) = 1/3; |121 − 110| = 11 > 10.
        assert_eq!(
            sub.apply(&img(vec![104, 121])).unwrap().as_u8().unwrap(),
            [0, 255]
        );
        let bg = sub.background().unwrap().unwrap();
        assert_eq!(bg.as_u8().unwrap(), [104, 114]);
    }

    #[test]
    fn running_average_matches_opencv_accumulate_weighted() {
        // cv2.accumulateWeighted(frame, acc, 0.5) over frames 1..5 from acc = frame 0 (frames
        // from numpy's default_rng(42)); with α = 0.5 the warm-up rate max(α, 1/n) is α from
        // frame 2 on. OpenCV's acc: 179.375, 197.25, 149.25, 110.5625, 89.4375, 137.8125,
        // 137.375, 53.5625, 87.8125, 106.5, 163.125, 176.375 (rounded half to even below).
        let frames: [[u8; 12]; 5] = [
            [22, 198, 167, 112, 110, 219, 22, 178, 51, 24, 134, 249],
            [188, 194, 183, 201, 131, 32, 214, 115, 128, 94, 46, 237],
            [200, 164, 103, 210, 139, 113, 115, 58, 23, 141, 227, 16],
            [219, 211, 70, 161, 42, 194, 179, 90, 17, 248, 114, 228],
            [173, 199, 194, 49, 93, 119, 127, 11, 139, 39, 190, 174],
        ];
        let config = BackgroundConfig {
            method: BackgroundMethod::RunningAverage,
            learning_rate: 0.5,
            ..BackgroundConfig::default()
        };
        let mut sub = BackgroundSubtractor::new(config).unwrap();
        for f in &frames {
            sub.apply(&Image::from_u8(4, 3, Channels::Gray, f.to_vec()).unwrap())
                .unwrap();
        }
        let bg = sub.background().unwrap().unwrap();
        assert_eq!(
            bg.as_u8().unwrap(),
            [179, 197, 149, 111, 89, 138, 137, 54, 88, 106, 163, 176]
        );
    }

    #[test]
    fn gaussian_hand_computed() {
        let config = BackgroundConfig {
            method: BackgroundMethod::Gaussian,
            learning_rate: 0.5,
            k_sigma: 2.0,
            initial_variance: 100.0,
            ..BackgroundConfig::default()
        };
        let mut sub = BackgroundSubtractor::new(config).unwrap();
        let img = |v: Vec<u8>| Image::from_u8(2, 1, Channels::Gray, v).unwrap();
        sub.apply(&img(vec![50, 50])).unwrap();
        // σ = 10, kσ = 20: 69 is background, 71 foreground.
        assert_eq!(
            sub.apply(&img(vec![69, 71])).unwrap().as_u8().unwrap(),
            [0, 255]
        );
        // μ = 50 + 0.5·19 = 59.5 → 60 (ties to even), σ² = 0.5·(100 + 0.5·361) = 140.25.
        let Some(Model::Gaussian { mean, var }) = &sub.model else {
            panic!("gaussian model");
        };
        assert_eq!(mean[0], 59.5);
        assert_eq!(var[0], 140.25);
    }

    #[test]
    fn mog_learns_a_bimodal_pixel() {
        // A pixel flickering between two levels is background once both modes are learned.
        let config = BackgroundConfig {
            method: BackgroundMethod::Mog,
            learning_rate: 0.05,
            background_ratio: 0.9,
            ..BackgroundConfig::default()
        };
        let mut sub = BackgroundSubtractor::new(config).unwrap();
        let img = |v: u8| Image::from_u8(1, 1, Channels::Gray, vec![v]).unwrap();
        let mut last = Vec::new();
        for f in 0..200 {
            let v = if f % 2 == 0 { 40 } else { 200 };
            last.push(sub.apply(&img(v)).unwrap().as_u8().unwrap()[0]);
        }
        assert!(last[150..].iter().all(|&m| m == 0), "{last:?}");
        // A new level is foreground.
        assert_eq!(sub.apply(&img(120)).unwrap().as_u8().unwrap(), [255]);
        // The components stay sorted by w/σ with weights summing to 1.
        let Some(Model::Mog { comps }) = &sub.model else {
            panic!("mog model");
        };
        let keys: Vec<f32> = comps.chunks_exact(3).map(|g| g[0] / g[1].sqrt()).collect();
        assert!(keys.windows(2).all(|k| k[0] >= k[1]), "{keys:?}");
        let total: f32 = comps.chunks_exact(3).map(|g| g[0]).sum();
        assert!((total - 1.0).abs() < 1e-5);
    }

    #[test]
    fn size_change_is_an_error_and_tiny_images_work() {
        let mut sub = BackgroundSubtractor::new(BackgroundConfig::default()).unwrap();
        let a = Image::from_u8(1, 1, Channels::Gray, vec![5]).unwrap();
        assert_eq!(sub.apply(&a).unwrap().as_u8().unwrap(), [0]);
        let b = Image::from_u8(2, 1, Channels::Gray, vec![5, 5]).unwrap();
        assert!(sub.apply(&b).unwrap_err().contains("first frame"));
        let c = Image::from_u16(1, 1, Channels::Gray, vec![5]).unwrap();
        assert!(sub.apply(&c).is_err());
        let mut sub = BackgroundSubtractor::new(BackgroundConfig::default()).unwrap();
        let empty = Image::from_u8(0, 0, Channels::Rgb, vec![]).unwrap();
        assert!(sub.apply(&empty).unwrap().is_empty());
        assert!(sub.apply(&empty).unwrap().is_empty());
        assert!(sub.background().unwrap().unwrap().is_empty());
        let nan = Image::from_f32(1, 1, Channels::Gray, vec![f32::NAN]).unwrap();
        assert!(sub.apply(&nan).is_err());
    }

    #[test]
    fn bad_params_are_rejected() {
        let bad = [
            ("learning_rate", ParamValue::Float(0.0)),
            ("learning_rate", ParamValue::Float(f64::NAN)),
            ("learning_rate", ParamValue::Float(1.5)),
            ("threshold", ParamValue::Float(f64::INFINITY)),
            ("k_sigma", ParamValue::Float(-1.0)),
            ("n_gaussians", ParamValue::Int(0)),
            ("n_gaussians", ParamValue::Int(9)),
            ("background_ratio", ParamValue::Float(0.0)),
            ("initial_variance", ParamValue::Float(1.0)),
        ];
        for (name, value) in bad {
            let mut map = BackgroundParams::default().to_map();
            map.insert(name.into(), value.clone());
            let result = BackgroundParams::from_map(&map).and_then(Background::new);
            assert!(result.is_err(), "{name} = {value:?} accepted");
        }
    }

    fn run_op(params: BackgroundParams, frames: Vec<Image>) -> Result<Outputs, OpError> {
        let op = Background::new(params).map_err(OpError::failed)?;
        let specs = Background::inputs();
        let items = frames.into_iter().map(Value::image).collect();
        let values = [Some(Value::list(PortType::Image, items))];
        let ctx = RunContext {
            node: "fg".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(&specs, &values))
    }

    #[test]
    fn operator_outputs_masks_and_background() {
        let (w, h) = (64, 48);
        let (frames, truth) = sequence(w, h, 3, 20, 10, 6.0);
        let images: Vec<Image> = frames
            .iter()
            .map(|f| to_image(f, w, h, 3, Depth::U8))
            .collect();
        let mut out = run_op(BackgroundParams::default(), images).unwrap();
        let Some(Value::List(masks)) = out.take("masks") else {
            panic!("no masks");
        };
        assert_eq!(masks.items.len(), 20);
        let Value::Image(last) = &masks.items[19] else {
            panic!("mask is not an image");
        };
        let hits = last
            .as_u8()
            .unwrap()
            .iter()
            .zip(&truth[19])
            .filter(|(m, t)| (**m == 255) == **t)
            .count();
        assert!(hits as f64 > 0.99 * (w * h) as f64);
        let Some(Value::Image(bg)) = out.take("background") else {
            panic!("no background");
        };
        assert_eq!(bg.format(), last_format(Channels::Rgb));
        assert!(run_op(BackgroundParams::default(), vec![]).is_err());
    }

    fn last_format(channels: Channels) -> ocellus_engine::value::PixelFormat {
        ocellus_engine::value::PixelFormat {
            channels,
            depth: Depth::U8,
        }
    }
}
