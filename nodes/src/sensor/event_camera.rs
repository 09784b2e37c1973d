//! `sensor.event_camera`: an event-camera (DVS) simulator over a rendered frame sequence, after
//! ESIM (Rebecq, Gehrig & Scaramuzza, "ESIM: an open event camera simulator", CoRL 2018).
//!
//! The algorithm is [`EventSimulator`] (a frame at a time); [`EventCamera`] is the thin
//! sequence operator around it.
//!
//! # Determinism
//!
//! Every pixel is simulated independently (rows in parallel); a frame interval's events are
//! gathered in row order and then stably sorted by time, so the event list is the same at any
//! thread count. Threshold mismatch is a counter-based hash of (seed, pixel index).

use std::sync::Arc;

use ocellus_engine::op::{
    Inputs, Op, OpError, Operator, Outputs, Packet, PortSpec, RunContext, SequenceState,
    run_sequence_batch,
};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Matrix, Metrics, PixelData, Value};
use rayon::prelude::*;

use crate::filter::grayscale::LumaStandard;
use crate::filter::noise::{gaussian_pairs, mix};

/// Smallest contrast threshold a pixel can get from threshold noise, log units.
pub const MIN_THRESHOLD: f64 = 0.01;

/// Salt of the threshold-mismatch stream.
const SALT_THRESHOLD: u64 = 0x7468_7265_7368_6F6C;

params! {
    /// Parameters of `sensor.event_camera`.
    pub struct EventCameraParams {
        /// Contrast threshold C: an event fires each time the log intensity moves by C from
        /// the pixel's reference, log units (0.1–0.5 for real sensors).
        contrast_threshold: f64 = 0.2 => [min = 0.01, max = 10.0],
        /// Standard deviation of the per-pixel threshold mismatch, log units; each pixel's
        /// positive and negative thresholds are C + σ·z (at least 0.01). 0 turns it off.
        threshold_sigma: f64 = 0.0 => [min = 0.0, max = 10.0],
        /// Refractory period: a pixel ignores crossings this soon after its last event (the
        /// reference still moves), s. 0 turns it off.
        refractory_s: f64 = 0.0 => [min = 0.0, unit = "s"],
        /// Frame rate of the input: frame k is at k / fps seconds.
        fps: f64 = 30.0 => [above = 0.0, unit = "frames/s"],
        /// Offset added to the intensity (in 0..1 of full scale) before the logarithm, so black
        /// pixels stay finite.
        log_eps: f64 = 0.001 => [above = 0.0],
        /// Seed of the threshold mismatch.
        seed: u64 = 0,
    }
}

/// Settings of the simulator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EventConfig {
    /// Contrast threshold, log units.
    pub contrast_threshold: f64,
    /// Per-pixel threshold mismatch standard deviation, log units.
    pub threshold_sigma: f64,
    /// Refractory period, s.
    pub refractory_s: f64,
    /// Frame rate, frames/s.
    pub fps: f64,
    /// Offset before the logarithm.
    pub log_eps: f64,
    /// Seed of the mismatch.
    pub seed: u64,
}

/// One event: pixel, time and polarity (+1 brighter, −1 darker).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Event {
    /// Column, px.
    pub x: u32,
    /// Row, px.
    pub y: u32,
    /// Time, s.
    pub t_s: f64,
    /// +1 or −1.
    pub polarity: i8,
}

/// Per-pixel state of the simulator.
#[derive(Debug, Clone, Copy)]
struct PixelState {
    /// Log intensity of the last frame.
    previous: f64,
    /// Reference level: the log intensity of the last crossing.
    reference: f64,
    /// Time of the last emitted event, s (−∞ before the first).
    last_event_s: f64,
    /// Thresholds for positive and negative events.
    threshold_pos: f64,
    threshold_neg: f64,
    /// Log intensity of the first frame.
    first: f64,
    /// Emitted events of each polarity.
    positive: u32,
    negative: u32,
}

/// An ESIM-style event simulator fed one log-intensity frame at a time.
#[derive(Debug, Clone)]
pub struct EventSimulator {
    config: EventConfig,
    width: usize,
    height: usize,
    pixels: Vec<PixelState>,
    previous_s: f64,
    events: Vec<Event>,
    suppressed: u64,
    frames: usize,
}

/// The per-pixel counts after a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct EventSummary {
    /// Per-pixel sum of polarities, row-major.
    pub accumulated: Vec<f32>,
    /// Positive events.
    pub positive: u64,
    /// Negative events.
    pub negative: u64,
    /// Crossings dropped by the refractory period.
    pub suppressed: u64,
    /// RMS over pixels of (first log frame + Σ polarity·threshold − last log frame), log units:
    /// how well integrating the events reconstructs the last frame.
    pub reconstruction_rms_log: f64,
}

impl EventSimulator {
    /// A simulator with no frame yet.
    pub fn new(config: EventConfig) -> EventSimulator {
        EventSimulator {
            config,
            width: 0,
            height: 0,
            pixels: Vec::new(),
            previous_s: 0.0,
            events: Vec::new(),
            suppressed: 0,
            frames: 0,
        }
    }

    /// Feeds the log intensity of the frame at `time_s` (`width` × `height`, row-major; later
    /// than the previous frame). The first frame sets the references and fires nothing.
    pub fn push(
        &mut self,
        log_frame: &[f64],
        width: usize,
        height: usize,
        time_s: f64,
    ) -> Result<(), String> {
        if log_frame.len() != width * height {
            return Err(format!(
                "frame has {} samples, expected {width}×{height}",
                log_frame.len()
            ));
        }
        if self.frames == 0 {
            self.start(log_frame, width, height);
            self.previous_s = time_s;
            self.frames = 1;
            return Ok(());
        }
        if (width, height) != (self.width, self.height) {
            return Err(format!(
                "frame is {width}×{height}, but the first frame was {}×{}",
                self.width, self.height
            ));
        }
        if time_s.is_nan() || time_s <= self.previous_s {
            return Err(format!(
                "frame time {time_s} s is not after the previous {} s",
                self.previous_s
            ));
        }
        let (t0, t1) = (self.previous_s, time_s);
        let config = self.config;
        let rows: Vec<(Vec<Event>, u64)> = self
            .pixels
            .par_chunks_mut(width)
            .zip(log_frame.par_chunks(width))
            .enumerate()
            .map(|(y, (states, logs))| {
                let mut events = Vec::new();
                let mut suppressed = 0;
                for (x, (state, &l1)) in states.iter_mut().zip(logs).enumerate() {
                    suppressed += simulate_pixel(state, l1, t0, t1, &config, |t_s, polarity| {
                        events.push(Event {
                            x: x as u32,
                            y: y as u32,
                            t_s,
                            polarity,
                        });
                    });
                }
                (events, suppressed)
            })
            .collect();
        let start = self.events.len();
        for (events, suppressed) in rows {
            self.events.extend(events);
            self.suppressed += suppressed;
        }
        // Stable: equal times keep row-major order.
        self.events[start..].sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
        self.previous_s = time_s;
        self.frames += 1;
        Ok(())
    }

    /// Initial state from the first frame, with the seeded threshold mismatch.
    fn start(&mut self, log_frame: &[f64], width: usize, height: usize) {
        self.width = width;
        self.height = height;
        let key = mix(self.config.seed ^ SALT_THRESHOLD);
        let c = self.config.contrast_threshold;
        let sigma = self.config.threshold_sigma;
        self.pixels = log_frame
            .par_iter()
            .enumerate()
            .map(|(i, &l)| {
                // One Box–Muller pair per pixel: positive and negative thresholds.
                let mut z = [0.0f32; 2];
                gaussian_pairs(key, i, &mut z);
                let threshold = |z: f32| (c + sigma * f64::from(z)).max(MIN_THRESHOLD);
                PixelState {
                    previous: l,
                    reference: l,
                    last_event_s: f64::NEG_INFINITY,
                    threshold_pos: if sigma > 0.0 { threshold(z[0]) } else { c },
                    threshold_neg: if sigma > 0.0 { threshold(z[1]) } else { c },
                    first: l,
                    positive: 0,
                    negative: 0,
                }
            })
            .collect();
    }

    /// Frames fed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Frame size (0 × 0 before the first frame).
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// The events so far, in time order.
    pub fn events(&self) -> &[Event] {
        &self.events
    }

    /// Per-pixel counts and the reconstruction error of the last frame.
    pub fn summary(&self) -> EventSummary {
        let accumulated = self
            .pixels
            .iter()
            .map(|p| p.positive as f32 - p.negative as f32)
            .collect();
        let (mut positive, mut negative, mut squared) = (0u64, 0u64, 0.0f64);
        for p in &self.pixels {
            positive += u64::from(p.positive);
            negative += u64::from(p.negative);
            let rebuilt = p.first + f64::from(p.positive) * p.threshold_pos
                - f64::from(p.negative) * p.threshold_neg;
            squared += (rebuilt - p.previous).powi(2);
        }
        EventSummary {
            accumulated,
            positive,
            negative,
            suppressed: self.suppressed,
            reconstruction_rms_log: (squared / self.pixels.len().max(1) as f64).sqrt(),
        }
    }
}

/// Moves one pixel from its previous log intensity to `l1` over [t0, t1]: every crossing of
/// reference ± threshold, taking the log intensity as linear in time between the frames, fires
/// an event at the interpolated time (`emit(t, polarity)`) unless it falls within the
/// refractory period of the last event; the reference moves to each crossing either way.
/// Returns the number of suppressed crossings.
fn simulate_pixel(
    state: &mut PixelState,
    l1: f64,
    t0: f64,
    t1: f64,
    config: &EventConfig,
    mut emit: impl FnMut(f64, i8),
) -> u64 {
    let l0 = state.previous;
    let slope = l1 - l0;
    let mut suppressed = 0;
    let mut fire = |state: &mut PixelState, level: f64, polarity: i8| {
        let fraction = if slope == 0.0 {
            1.0
        } else {
            ((level - l0) / slope).clamp(0.0, 1.0)
        };
        let t = t0 + fraction * (t1 - t0);
        state.reference = level;
        if t - state.last_event_s < config.refractory_s {
            suppressed += 1;
            return;
        }
        state.last_event_s = t;
        if polarity > 0 {
            state.positive += 1;
        } else {
            state.negative += 1;
        }
        emit(t, polarity);
    };
    while l1 >= state.reference + state.threshold_pos {
        let level = state.reference + state.threshold_pos;
        fire(state, level, 1);
    }
    while l1 <= state.reference - state.threshold_neg {
        let level = state.reference - state.threshold_neg;
        fire(state, level, -1);
    }
    state.previous = l1;
    suppressed
}

/// ln(luma + eps) of a frame, luma (BT.601 for colour, alpha ignored) in 0..1 of full scale
/// (u8 / 255, u16 / 65535, f32 as is, clamped at 0). f32 samples must be finite.
pub fn log_intensity(frame: &Image, log_eps: f64) -> Result<Vec<f64>, String> {
    let stride = frame.channels().count();
    let (scale, samples): (f64, Vec<f64>) = match frame.data() {
        PixelData::U8(v) => (1.0 / 255.0, v.iter().map(|&s| f64::from(s)).collect()),
        PixelData::U16(v) => (1.0 / 65535.0, v.iter().map(|&s| f64::from(s)).collect()),
        PixelData::F32(v) => {
            if v.iter().any(|s| !s.is_finite()) {
                return Err("contains NaN or infinite samples".into());
            }
            (1.0, v.iter().map(|&s| f64::from(s)).collect())
        }
    };
    let weights = LumaStandard::Bt601.weights();
    Ok(samples
        .par_chunks(stride)
        .map(|px| {
            let luma = if stride >= 3 {
                weights[0] * px[0] + weights[1] * px[1] + weights[2] * px[2]
            } else {
                px[0]
            };
            ((luma * scale).max(0.0) + log_eps).ln()
        })
        .collect())
}

/// Event-camera simulation over a frame sequence (`sensor.event_camera`). See
/// [`EventSimulator`].
#[derive(Debug, Clone, PartialEq)]
pub struct EventCamera {
    config: EventConfig,
}

impl Op for EventCamera {
    type Params = EventCameraParams;
    const ID: &'static str = "sensor.event_camera";
    const SUMMARY: &'static str = "Simulates an event camera (DVS) over a frame sequence: log-intensity threshold crossings with interpolated timestamps.";
    const DOC: &'static str = r#"
Each pixel keeps a reference log intensity L_ref (the first frame's value at the start). Between
consecutive frames k−1 and k (at (k−1)/fps and k/fps s) the log intensity L = ln(luma + log_eps)
is taken as linear in time; every time it reaches L_ref + C⁺ (or L_ref − C⁻) an event
(x, y, t, +1) (or −1) fires at the interpolated time and L_ref moves to that level, as in ESIM
(H. Rebecq, D. Gehrig, D. Scaramuzza, "ESIM: an open event camera simulator", CoRL 2018) and
the DVS pixel of P. Lichtsteiner, C. Posch, T. Delbruck, "A 128×128 120 dB 15 µs latency
asynchronous temporal contrast vision sensor", IEEE JSSC 43(2), 2008. A pixel whose log
intensity ramps by ΔL fires ⌊|ΔL|/C⌋ events of the sign of ΔL. C⁺ and C⁻ are
`contrast_threshold` plus per-pixel Gaussian mismatch of `threshold_sigma` (seeded, at least
0.01). Crossings within `refractory_s` of the pixel's last event are dropped (counted as
`suppressed`; the reference still moves). Luma is BT.601 of u8/255, u16/65535 or f32
samples.

Outputs after the last frame: `events`, an n×4 matrix of rows (x, y, t_s, polarity) in time
order (ties in row-major pixel order); `accumulated`, the per-pixel polarity sum (f32 gray);
`metrics`: `events`, `positive`, `negative`, `suppressed`, `frames`, `duration_s`,
`event_rate_per_pixel_s`, and `reconstruction_rms_log`, the RMS (log units) of the last frame
rebuilt by integrating the events (first frame + Σ polarity·threshold) against the truth —
below C without refractory drops. A static scene gives no events.

Example:
    "dvs": (op: "sensor.event_camera", inputs: { "frames": "clip.frames" }, params: (contrast_threshold: 0.15, fps: 30)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "frames",
                PortType::Image.list_of(),
                "The frames in time order, all of one size; gray or colour, u8, u16 or f32.",
            )
            .per_frame(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "events",
                PortType::Matrix,
                "n×4 events (x, y, t_s, polarity ±1), in time order.",
            ),
            PortSpec::new(
                "accumulated",
                PortType::Image,
                "Per-pixel sum of event polarities, f32 gray.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "events, positive, negative, suppressed, frames, duration_s, event_rate_per_pixel_s, reconstruction_rms_log.",
            ),
        ]
    }

    fn new(params: EventCameraParams) -> Result<Self, String> {
        let EventCameraParams {
            contrast_threshold,
            threshold_sigma,
            refractory_s,
            fps,
            log_eps,
            seed,
        } = params;
        if !(contrast_threshold.is_finite() && contrast_threshold >= MIN_THRESHOLD) {
            return Err(format!(
                "`contrast_threshold` must be finite and ≥ {MIN_THRESHOLD}, got {contrast_threshold}"
            ));
        }
        for (name, v) in [
            ("threshold_sigma", threshold_sigma),
            ("refractory_s", refractory_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("`{name}` must be finite and ≥ 0, got {v}"));
            }
        }
        for (name, v) in [("fps", fps), ("log_eps", log_eps)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("`{name}` must be finite and > 0, got {v}"));
            }
        }
        Ok(EventCamera {
            config: EventConfig {
                contrast_threshold,
                threshold_sigma,
                refractory_s,
                fps,
                log_eps,
                seed,
            },
        })
    }
}

impl Operator for EventCamera {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        run_sequence_batch(self, ctx, inputs, &Self::outputs())
    }

    fn sequence(
        &self,
        _ctx: &RunContext,
        _inputs: &Inputs<'_>,
    ) -> Option<Result<Box<dyn SequenceState>, OpError>> {
        Some(Ok(
            Box::new(EventSimulator::new(self.config)) as Box<dyn SequenceState>
        ))
    }
}

impl SequenceState for EventSimulator {
    fn push(
        &mut self,
        _ctx: &RunContext,
        packet: Packet,
        inputs: &Inputs<'_>,
    ) -> Result<Outputs, OpError> {
        let frame = inputs.image("frames")?;
        let fail = |e: String| OpError::input("frames", format!("frame {}: {e}", packet.index));
        if frame.is_empty() {
            return Err(fail("is empty".into()));
        }
        let log = log_intensity(frame, self.config.log_eps).map_err(fail)?;
        let time_s = packet.index as f64 / self.config.fps;
        EventSimulator::push(self, &log, frame.width(), frame.height(), time_s).map_err(fail)?;
        Ok(Outputs::new())
    }

    fn finish(&mut self, _ctx: &RunContext) -> Result<Outputs, OpError> {
        if self.frames == 0 {
            return Err(OpError::input("frames", "no frames"));
        }
        let summary = self.summary();
        let data: Vec<f64> = self
            .events
            .iter()
            .flat_map(|e| [f64::from(e.x), f64::from(e.y), e.t_s, f64::from(e.polarity)])
            .collect();
        let events = Matrix::new(self.events.len(), 4, data)
            .map_err(|e| OpError::failed(format!("building the event matrix: {e}")))?;
        let accumulated =
            Image::from_f32(self.width, self.height, Channels::Gray, summary.accumulated)
                .map_err(|e| OpError::failed(format!("building the event image: {e}")))?;
        let duration_s = (self.frames - 1) as f64 / self.config.fps;
        let pixels = (self.width * self.height) as f64;
        let total = summary.positive + summary.negative;
        let rate = if duration_s > 0.0 {
            total as f64 / (pixels * duration_s)
        } else {
            0.0
        };
        let metrics: Metrics = [
            ("events", total as f64),
            ("positive", summary.positive as f64),
            ("negative", summary.negative as f64),
            ("suppressed", summary.suppressed as f64),
            ("frames", self.frames as f64),
            ("duration_s", duration_s),
            ("event_rate_per_pixel_s", rate),
            ("reconstruction_rms_log", summary.reconstruction_rms_log),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        Ok(Outputs::new()
            .with("events", Value::Matrix(Arc::new(events)))
            .with("accumulated", Value::image(accumulated))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(c: f64) -> EventConfig {
        EventConfig {
            contrast_threshold: c,
            threshold_sigma: 0.0,
            refractory_s: 0.0,
            fps: 10.0,
            log_eps: 1e-3,
            seed: 0,
        }
    }

    #[test]
    fn a_log_ramp_fires_floor_delta_over_c_events_at_interpolated_times() {
        // One pixel ramps its log intensity by ΔL = 1.05 over one interval [0, 0.1] s, another
        // by −0.7 over two intervals, a third stays still.
        let c = 0.2;
        let mut sim = EventSimulator::new(config(c));
        sim.push(&[0.0, 0.0, -1.0], 3, 1, 0.0).unwrap();
        sim.push(&[1.05, -0.35, -1.0], 3, 1, 0.1).unwrap();
        sim.push(&[1.05, -0.7, -1.0], 3, 1, 0.2).unwrap();
        let events = sim.events();
        let first: Vec<&Event> = events.iter().filter(|e| e.x == 0).collect();
        assert_eq!(first.len(), 5, "⌊1.05 / 0.2⌋");
        for (j, e) in first.iter().enumerate() {
            assert_eq!(e.polarity, 1);
            // Crossing of level 0.2·(j+1) on the ramp 0 → 1.05 over 0.1 s.
            let t = 0.1 * 0.2 * (j + 1) as f64 / 1.05;
            assert!((e.t_s - t).abs() < 1e-12, "{} vs {t}", e.t_s);
        }
        let second: Vec<&Event> = events.iter().filter(|e| e.x == 1).collect();
        assert_eq!(second.len(), 3, "⌊0.7 / 0.2⌋");
        assert!(second.iter().all(|e| e.polarity == -1));
        // Levels −0.2 (t = 0.2/0.35·0.1), −0.4 (in the second interval), −0.6.
        let times = [
            0.1 * 0.2 / 0.35,
            0.1 + 0.1 * 0.05 / 0.35,
            0.1 + 0.1 * 0.25 / 0.35,
        ];
        for (e, t) in second.iter().zip(times) {
            assert!((e.t_s - t).abs() < 1e-12, "{} vs {t}", e.t_s);
        }
        assert!(events.iter().all(|e| e.x != 2));
        assert!(events.windows(2).all(|w| w[0].t_s <= w[1].t_s));
        let s = sim.summary();
        assert_eq!(s.accumulated, vec![5.0, -3.0, 0.0]);
        assert_eq!((s.positive, s.negative), (5, 3));
        // Rebuilt: 1.0 vs 1.05 and −0.6 vs −0.7.
        let rms = ((0.05f64.powi(2) + 0.1f64.powi(2)) / 3.0).sqrt();
        assert!((s.reconstruction_rms_log - rms).abs() < 1e-9);
    }

    #[test]
    fn a_static_scene_fires_nothing() {
        let frame = Image::from_u8(
            16,
            8,
            Channels::Rgb,
            (0..16 * 8 * 3).map(|i| (i % 251) as u8).collect(),
        )
        .unwrap();
        let log = log_intensity(&frame, 1e-3).unwrap();
        let mut sim = EventSimulator::new(EventConfig {
            threshold_sigma: 0.05,
            ..config(0.1)
        });
        for k in 0..5 {
            sim.push(&log, 16, 8, k as f64 * 0.1).unwrap();
        }
        assert!(sim.events().is_empty());
        assert_eq!(sim.summary().reconstruction_rms_log, 0.0);
    }

    #[test]
    fn refractory_period_drops_close_events() {
        // ΔL = 1.0 in 0.1 s with C = 0.1: crossings every 0.01 s; a 0.025 s refractory period
        // keeps every third.
        let mut sim = EventSimulator::new(EventConfig {
            refractory_s: 0.025,
            ..config(0.1)
        });
        sim.push(&[0.0], 1, 1, 0.0).unwrap();
        sim.push(&[1.05], 1, 1, 0.1).unwrap();
        let times: Vec<f64> = sim.events().iter().map(|e| e.t_s).collect();
        assert_eq!(times.len(), 4, "{times:?}");
        assert_eq!(sim.summary().suppressed, 10 - 4);
    }

    #[test]
    fn threshold_noise_is_seeded_and_thread_independent() {
        let (w, h) = (40, 30);
        let frames: Vec<Vec<f64>> = (0..4)
            .map(|k| {
                (0..w * h)
                    .map(|i| ((i % w) as f64 * 0.05 + k as f64 * 0.3).sin())
                    .collect()
            })
            .collect();
        let run = |threads: usize, seed: u64| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    let mut sim = EventSimulator::new(EventConfig {
                        threshold_sigma: 0.03,
                        seed,
                        ..config(0.1)
                    });
                    for (k, f) in frames.iter().enumerate() {
                        sim.push(f, w, h, k as f64 * 0.1).unwrap();
                    }
                    sim.events().to_vec()
                })
        };
        let a = run(1, 4);
        assert!(!a.is_empty());
        assert_eq!(a, run(3, 4));
        assert_ne!(a, run(1, 5));
    }

    #[test]
    fn bad_frames_and_params_are_rejected() {
        let mut sim = EventSimulator::new(config(0.2));
        sim.push(&[0.0; 4], 2, 2, 0.0).unwrap();
        assert!(
            sim.push(&[0.0; 6], 3, 2, 0.1)
                .unwrap_err()
                .contains("first frame")
        );
        assert!(
            sim.push(&[0.0; 4], 2, 2, 0.0)
                .unwrap_err()
                .contains("not after")
        );
        assert!(sim.push(&[0.0; 3], 2, 2, 0.2).is_err());
        let nan = Image::from_f32(1, 1, Channels::Gray, vec![f32::NAN]).unwrap();
        assert!(log_intensity(&nan, 1e-3).is_err());
        let p = |f: fn(&mut EventCameraParams)| {
            let mut p = EventCameraParams::default();
            f(&mut p);
            EventCamera::new(p)
        };
        assert!(
            p(|p| p.contrast_threshold = 0.0)
                .unwrap_err()
                .contains("contrast")
        );
        assert!(p(|p| p.fps = 0.0).unwrap_err().contains("fps"));
        assert!(
            p(|p| p.refractory_s = f64::NAN)
                .unwrap_err()
                .contains("refractory")
        );
        assert!(p(|p| p.log_eps = -1.0).unwrap_err().contains("log_eps"));
    }

    #[test]
    fn operator_runs_on_a_moving_sequence() {
        use crate::capture::moving::{MovingShapes, MovingShapesParams};
        let clip = MovingShapes::new(MovingShapesParams {
            width: 64,
            height: 48,
            frames: 6,
            size_px: 12,
            noise_sigma: 0.0,
            ..MovingShapesParams::default()
        })
        .unwrap();
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let mut clip_out = clip.run(&ctx, &Inputs::new(&[], &[])).unwrap();
        let frames = clip_out.take("frames").unwrap();
        let op = EventCamera::new(EventCameraParams::default()).unwrap();
        let specs = EventCamera::inputs();
        let mut out = op.run(&ctx, &Inputs::new(&specs, &[Some(frames)])).unwrap();
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("metrics");
        };
        let Some(Value::Matrix(events)) = out.take("events") else {
            panic!("events");
        };
        // Moving bright squares on a static background: events, both signs (leading and
        // trailing edges), all within the 5 intervals.
        assert!(m["positive"] > 0.0 && m["negative"] > 0.0, "{m:?}");
        assert_eq!(events.rows as f64, m["events"]);
        assert!((0..events.rows).all(|r| {
            let t = events.get(r, 2).unwrap();
            t > 0.0 && t <= 5.0 / 30.0 + 1e-12
        }));
        assert_eq!(m["frames"], 6.0);
    }
}
