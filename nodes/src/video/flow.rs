//! Dense optical flow fields and the machinery shared by `video.flow_horn_schunck` and
//! `video.flow_lk`: the coarse-to-fine image pyramid of a frame pair, flow upsampling between
//! levels, warping of the second frame by a flow, median filtering of a flow and the Middlebury
//! colour coding.
//!
//! A flow is two gray f32 planes `u` (x component) and `v` (y component) in px: the content at
//! pixel (x, y) of `previous` is at (x + u, y + v) in `next`. Operators output them as two gray
//! f32 images `u` and `v`, the convention of `video.block_match` (and of the `vx` / `vy` inputs of
//! `filter.lic`).
//!
//! How it runs: every pass works on fixed bands of [`BAND_ROWS`] rows in parallel and each
//! output sample depends only on its inputs, so results are bit-identical for any thread count.

use ocellus_engine::value::{Channels, Image, PixelData};
use rayon::prelude::*;

use super::gray::{Plane, gray_f32, plane_of, pyramid};
use crate::filter::border::BorderMode;
use crate::filter::gaussian::gaussian_blur;
use crate::filter::median::median_blur;
use crate::filter::resize::{Interpolation, Target, resize};

/// Rows per parallel band.
pub const BAND_ROWS: usize = 16;

/// Smallest side of a pyramid level, px: coarser levels are not built.
pub const MIN_LEVEL_SIDE: usize = 8;

/// Largest number of pyramid levels above the base.
pub const MAX_LEVELS: u32 = 16;

/// Smallest and largest pyramid scale factor.
pub const SCALE_RANGE: (f64, f64) = (0.25, 0.95);

/// A dense flow field: `u`, `v` in px, row-major, `width × height` each.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowField {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Horizontal displacement, px.
    pub u: Vec<f32>,
    /// Vertical displacement, px.
    pub v: Vec<f32>,
}

impl FlowField {
    /// The zero flow of a `width × height` frame.
    pub fn zeros(width: usize, height: usize) -> FlowField {
        FlowField {
            width,
            height,
            u: vec![0.0; width * height],
            v: vec![0.0; width * height],
        }
    }

    /// `u` and `v` as gray f32 images.
    pub fn to_images(&self) -> Result<(Image, Image), String> {
        let image = |d: &Vec<f32>| {
            Image::from_f32(self.width, self.height, Channels::Gray, d.clone())
                .map_err(|e| e.to_string())
        };
        Ok((image(&self.u)?, image(&self.v)?))
    }
}

/// Checks that both frames have the same size.
pub fn check_pair(previous: &Image, next: &Image) -> Result<(), String> {
    if previous.width() != next.width() || previous.height() != next.height() {
        return Err(format!(
            "`previous` is {}×{} but `next` is {}×{}",
            previous.width(),
            previous.height(),
            next.width(),
            next.height()
        ));
    }
    Ok(())
}

/// Checks a `levels` / `scale` pair of parameters.
pub fn check_pyramid_params(levels: u32, scale: f64) -> Result<(), String> {
    if levels > MAX_LEVELS {
        return Err(format!(
            "`levels` must be at most {MAX_LEVELS}, got {levels}"
        ));
    }
    let (lo, hi) = SCALE_RANGE;
    if !scale.is_finite() || !(lo..=hi).contains(&scale) {
        return Err(format!(
            "`scale` must be a finite number in [{lo}, {hi}], got {scale}"
        ));
    }
    Ok(())
}

/// One pyramid level of a frame pair (gray f32, 0–255 scale).
#[derive(Debug, Clone)]
pub struct FlowLevel {
    /// `previous` at this level.
    pub prev: Plane,
    /// `next` at this level.
    pub next: Plane,
    /// Map from the next finer level: a finer pixel at (x, y) sits at
    /// `(x·ratio[0] + offset[0], y·ratio[1] + offset[1])` on this level (unused on level 0).
    pub ratio: [f32; 2],
    /// See `ratio`.
    pub offset: [f32; 2],
}

/// Builds the coarse-to-fine pyramid of a frame pair: level 0 the full-resolution gray planes,
/// then at most `levels` levels each `scale` times the size of the one below, stopping before a
/// side would drop below [`MIN_LEVEL_SIDE`]. `scale == 0.5` uses `pyrDown` steps (5×5 binomial
/// blur, even pixels kept); other factors a Gaussian blur of σ = 1/√(2·scale) px followed by
/// bilinear resampling on pixel centres.
pub fn flow_pyramid(
    previous: &Image,
    next: &Image,
    levels: usize,
    scale: f64,
) -> Result<Vec<FlowLevel>, String> {
    let a = gray_f32(previous);
    let b = gray_f32(next);
    if (scale - 0.5).abs() < 1e-12 {
        let pa = pyramid(&a, levels, MIN_LEVEL_SIDE)?;
        let pb = pyramid(&b, levels, MIN_LEVEL_SIDE)?;
        return Ok(pa
            .into_iter()
            .zip(pb)
            .map(|(prev, next)| FlowLevel {
                prev,
                next,
                ratio: [0.5, 0.5],
                offset: [0.0, 0.0],
            })
            .collect());
    }
    let mut out = vec![FlowLevel {
        prev: a,
        next: b,
        ratio: [1.0, 1.0],
        offset: [0.0, 0.0],
    }];
    let sigma = (1.0 / (2.0 * scale)).sqrt();
    while out.len() <= levels {
        let Some(last) = out.last() else { break };
        let (w, h) = (last.prev.width, last.prev.height);
        let nw = (w as f64 * scale).round() as usize;
        let nh = (h as f64 * scale).round() as usize;
        if nw < MIN_LEVEL_SIDE || nh < MIN_LEVEL_SIDE {
            break;
        }
        let shrink = |p: &Plane| -> Result<Plane, String> {
            let blurred = gaussian_blur(
                &p.to_image()?,
                sigma,
                sigma,
                0,
                0,
                BorderMode::Reflect101,
                0.0,
            );
            Ok(plane_of(&resize(
                &blurred,
                Target::Size(nw, nh),
                Interpolation::Bilinear,
            )?))
        };
        let (rx, ry) = (nw as f32 / w as f32, nh as f32 / h as f32);
        let level = FlowLevel {
            prev: shrink(&last.prev)?,
            next: shrink(&last.next)?,
            ratio: [rx, ry],
            offset: [0.5 * rx - 0.5, 0.5 * ry - 0.5],
        };
        out.push(level);
    }
    Ok(out)
}

/// The flow of a coarser level resampled (bilinearly, edge replicated) onto the `width ×
/// height` finer level mapped by `coarse` ([`FlowLevel::ratio`] / `offset`), its vectors scaled
/// to finer-level pixels.
pub fn upsample(flow: &FlowField, width: usize, height: usize, coarse: &FlowLevel) -> FlowField {
    let mut out = FlowField::zeros(width, height);
    if width == 0 || height == 0 || flow.width == 0 || flow.height == 0 {
        return out;
    }
    let pu = Plane {
        width: flow.width,
        height: flow.height,
        data: flow.u.clone(),
    };
    let pv = Plane {
        width: flow.width,
        height: flow.height,
        data: flow.v.clone(),
    };
    let [rx, ry] = coarse.ratio;
    let [ox, oy] = coarse.offset;
    let (sx, sy) = (1.0 / rx, 1.0 / ry);
    out.u
        .par_chunks_mut(BAND_ROWS * width)
        .zip(out.v.par_chunks_mut(BAND_ROWS * width))
        .enumerate()
        .for_each(|(band, (bu, bv))| {
            for (r, (ru, rv)) in bu
                .chunks_exact_mut(width)
                .zip(bv.chunks_exact_mut(width))
                .enumerate()
            {
                let cy = (band * BAND_ROWS + r) as f32 * ry + oy;
                for (x, (u, v)) in ru.iter_mut().zip(rv.iter_mut()).enumerate() {
                    let cx = x as f32 * rx + ox;
                    *u = pu.bilinear(cx, cy) * sx;
                    *v = pv.bilinear(cx, cy) * sy;
                }
            }
        });
    out
}

/// Samples the `K` planes (all the size of `flow`) at `(x + u, y + v)` for every pixel,
/// bicubically (Catmull–Rom: Keys' cubic with a = −0.5) with the edge replicated; the
/// sample point is clamped to the frame first. Bicubic rather than bilinear: bilinear
/// interpolation shifts the phase of the warped image by a fraction-dependent amount, which
/// biases sub-pixel flow by a few hundredths of a pixel. The flag is false where the point lies
/// outside the frame (`[0, w − 1] × [0, h − 1]`) or is not finite.
pub fn warp<const K: usize>(planes: [&Plane; K], flow: &FlowField) -> Vec<([f32; K], bool)> {
    let (w, h) = (flow.width, flow.height);
    let mut out = vec![([0.0f32; K], false); w * h];
    if w == 0 || h == 0 {
        return out;
    }
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    out.par_chunks_mut(BAND_ROWS * w)
        .enumerate()
        .for_each(|(band, rows)| {
            for (r, row) in rows.chunks_exact_mut(w).enumerate() {
                let y = band * BAND_ROWS + r;
                let fu = &flow.u[y * w..][..w];
                let fv = &flow.v[y * w..][..w];
                for (x, o) in row.iter_mut().enumerate() {
                    let sx = x as f32 + fu[x];
                    let sy = y as f32 + fv[x];
                    let inside = (0.0..=xmax).contains(&sx) && (0.0..=ymax).contains(&sy);
                    let (sx, sy) = if sx.is_finite() && sy.is_finite() {
                        (sx.clamp(0.0, xmax), sy.clamp(0.0, ymax))
                    } else {
                        (x as f32, y as f32)
                    };
                    *o = (bicubic(planes, sx, sy), inside);
                }
            }
        });
    out
}

/// Catmull–Rom weights (Keys' cubic with a = −0.5, the third-order accurate one) for fraction
/// `t` ∈ [0, 1), taps at −1, 0, 1, 2.
#[inline]
fn catmull_rom(t: f32) -> [f32; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// Bicubic samples of `K` same-size planes at (x, y) inside the frame; taps beyond the edge
/// read the edge pixel.
#[inline]
fn bicubic<const K: usize>(planes: [&Plane; K], x: f32, y: f32) -> [f32; K] {
    let Some(first) = planes.first() else {
        return [0.0; K];
    };
    let (w, h) = (first.width, first.height);
    let (x0, y0) = (x.floor(), y.floor());
    let wx = catmull_rom(x - x0);
    let wy = catmull_rom(y - y0);
    let (x0, y0) = (x0 as isize, y0 as isize);
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    let xs: [usize; 4] = std::array::from_fn(|k| clamp(x0 + k as isize - 1, w));
    let ys: [usize; 4] = std::array::from_fn(|k| clamp(y0 + k as isize - 1, h) * w);
    planes.map(|p| {
        let mut acc = 0.0f32;
        for (ry, cy) in ys.iter().zip(wy) {
            let row = &p.data[*ry..];
            let s =
                row[xs[0]] * wx[0] + row[xs[1]] * wx[1] + row[xs[2]] * wx[2] + row[xs[3]] * wx[3];
            acc += s * cy;
        }
        acc
    })
}

/// Median filter of both components of a flow over `ksize × ksize` windows (odd; reflect-101
/// border), as `filter.median`.
pub fn median_flow(flow: &FlowField, ksize: usize) -> Result<FlowField, String> {
    if ksize <= 1 || flow.width == 0 || flow.height == 0 {
        return Ok(flow.clone());
    }
    let (iu, iv) = flow.to_images()?;
    let take = |image: &Image| -> Vec<f32> {
        plane_of(&median_blur(image, ksize, BorderMode::Reflect101, 0.0)).data
    };
    Ok(FlowField {
        width: flow.width,
        height: flow.height,
        u: take(&iu),
        v: take(&iv),
    })
}

/// Colours of the Middlebury wheel: (segment length, from, to) per hue segment
/// red → yellow → green → cyan → blue → magenta → red.
const WHEEL: [(usize, [u8; 3], [u8; 3]); 6] = [
    (15, [255, 0, 0], [255, 255, 0]),
    (6, [255, 255, 0], [0, 255, 0]),
    (4, [0, 255, 0], [0, 255, 255]),
    (11, [0, 255, 255], [0, 0, 255]),
    (13, [0, 0, 255], [255, 0, 255]),
    (6, [255, 0, 255], [255, 0, 0]),
];

/// The 55 colours of the Middlebury colour wheel, in [0, 1].
fn wheel() -> Vec<[f32; 3]> {
    let mut out = Vec::with_capacity(55);
    for (n, from, to) in WHEEL {
        for i in 0..n {
            let t = i as f32 / n as f32;
            out.push(std::array::from_fn(|c| {
                let (a, b) = (f32::from(from[c]), f32::from(to[c]));
                // The wheel's ramps run in integer steps, as the Middlebury code builds them.
                (a + ((b - a) * t).floor()) / 255.0
            }));
        }
    }
    out
}

/// Middlebury colour coding of a flow (Baker et al. 2011): hue from the direction (the
/// 55-colour wheel, interpolated), saturation from the length normalised by the largest finite
/// length in the field (white = no motion, full colour = the largest motion). Non-finite vectors
/// are black. RGB u8.
pub fn flow_to_color(flow: &FlowField) -> Result<Image, String> {
    let wheel = wheel();
    let n = wheel.len();
    let max_rad = flow
        .u
        .iter()
        .zip(&flow.v)
        .map(|(u, v)| (u * u + v * v).sqrt())
        .filter(|r| r.is_finite())
        .fold(0.0f32, f32::max);
    let norm = if max_rad > 0.0 { 1.0 / max_rad } else { 1.0 };
    let mut data = vec![0u8; flow.width * flow.height * 3];
    data.par_chunks_mut(3 * flow.width.max(1) * BAND_ROWS)
        .zip(flow.u.par_chunks(flow.width.max(1) * BAND_ROWS))
        .zip(flow.v.par_chunks(flow.width.max(1) * BAND_ROWS))
        .for_each(|((out, bu), bv)| {
            for ((px, &u), &v) in out.chunks_exact_mut(3).zip(bu).zip(bv) {
                let (u, v) = (u * norm, v * norm);
                if !u.is_finite() || !v.is_finite() {
                    continue;
                }
                let rad = (u * u + v * v).sqrt();
                let a = (-v).atan2(-u) / std::f32::consts::PI;
                let fk = (a + 1.0) / 2.0 * (n - 1) as f32;
                let k0 = (fk.floor() as usize).min(n - 1);
                let k1 = (k0 + 1) % n;
                let f = fk - k0 as f32;
                for c in 0..3 {
                    let col = (1.0 - f) * wheel[k0][c] + f * wheel[k1][c];
                    let col = if rad <= 1.0 {
                        1.0 - rad * (1.0 - col)
                    } else {
                        col * 0.75
                    };
                    px[c] = (255.0 * col).round().clamp(0.0, 255.0) as u8;
                }
            }
        });
    Image::new(flow.width, flow.height, Channels::Rgb, PixelData::U8(data))
        .map_err(|e| e.to_string())
}

#[cfg(test)]
pub(crate) mod test_support {
    //! Known-motion frame pairs and end-point errors for the dense flow tests.

    use super::FlowField;
    use crate::video::synth::blob_texture;
    use ocellus_engine::value::Image;

    /// The identity texture map.
    pub const IDENTITY: [f64; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

    /// A frame pair `(previous, next)` of the blob texture (σ 3 px, seed `seed`) where `next`
    /// shows the texture through `map` (`previous` through the identity), and the true flow:
    /// the point at `p` in `previous` (texture point `p`) is at `A⁻¹(p − c)` in `next`.
    pub fn pair(w: usize, h: usize, seed: u64, map: [f64; 6]) -> (Image, Image, FlowField) {
        let a = blob_texture(w, h, 3.0, seed, IDENTITY).unwrap();
        let b = blob_texture(w, h, 3.0, seed, map).unwrap();
        let det = map[0] * map[4] - map[1] * map[3];
        let mut truth = FlowField::zeros(w, h);
        for y in 0..h {
            for x in 0..w {
                let (px, py) = (x as f64 - map[2], y as f64 - map[5]);
                let qx = (map[4] * px - map[1] * py) / det;
                let qy = (-map[3] * px + map[0] * py) / det;
                truth.u[y * w + x] = (qx - x as f64) as f32;
                truth.v[y * w + x] = (qy - y as f64) as f32;
            }
        }
        (a, b, truth)
    }

    /// Content moving by `(dx, dy)` px.
    pub fn translation(dx: f64, dy: f64) -> [f64; 6] {
        [1.0, 0.0, -dx, 0.0, 1.0, -dy]
    }

    /// Content rotated by `degrees` about `(cx, cy)`.
    pub fn rotation(degrees: f64, cx: f64, cy: f64) -> [f64; 6] {
        let t = degrees.to_radians();
        let (c, s) = (t.cos(), t.sin());
        [c, s, cx - c * cx - s * cy, -s, c, cy + s * cx - c * cy]
    }

    /// Mean end-point error of `flow` against `truth` over the pixels at least `margin` px
    /// inside the frame.
    pub fn epe(flow: &FlowField, truth: &FlowField, margin: usize) -> f32 {
        let (w, h) = (flow.width, flow.height);
        let mut sum = 0.0f64;
        let mut count = 0usize;
        for y in margin..h - margin {
            for x in margin..w - margin {
                let i = y * w + x;
                let du = flow.u[i] - truth.u[i];
                let dv = flow.v[i] - truth.v[i];
                sum += f64::from((du * du + dv * dv).sqrt());
                count += 1;
            }
        }
        (sum / count.max(1) as f64) as f32
    }

    /// Asserts two flows are bit-identical.
    pub fn assert_bit_identical(a: &FlowField, b: &FlowField) {
        assert_eq!((a.width, a.height), (b.width, b.height));
        for (x, y) in a.u.iter().chain(&a.v).zip(b.u.iter().chain(&b.v)) {
            assert_eq!(x.to_bits(), y.to_bits());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::test_support::*;
    use super::*;

    #[test]
    fn truth_of_a_translation() {
        let (_, _, t) = pair(20, 10, 1, translation(1.5, -0.25));
        assert!(t.u.iter().all(|&u| (u - 1.5).abs() < 1e-6));
        assert!(t.v.iter().all(|&v| (v + 0.25).abs() < 1e-6));
    }

    #[test]
    fn warp_by_the_true_flow_reproduces_previous() {
        let (a, b, truth) = pair(64, 48, 3, translation(2.0, 1.0));
        let (pa, pb) = (gray_f32(&a), gray_f32(&b));
        let warped = warp([&pb], &truth);
        for y in 0..48 - 1 {
            for x in 0..64 - 2 {
                let (s, inside) = warped[y * 64 + x];
                assert!(inside);
                assert!((s[0] - pa.data[y * 64 + x]).abs() < 1e-3);
            }
        }
        assert!(!warped[64 - 1].1, "the last column maps outside");
    }

    #[test]
    fn pyramids_and_upsampling() {
        let (a, b, _) = pair(100, 60, 2, IDENTITY);
        for scale in [0.5, 0.75] {
            let levels = flow_pyramid(&a, &b, 5, scale).unwrap();
            assert!(levels.len() >= 2);
            for l in &levels {
                assert!(l.prev.width >= MIN_LEVEL_SIDE && l.prev.height >= MIN_LEVEL_SIDE);
            }
            // A constant flow upsamples to the constant scaled by the size ratio.
            let (cw, ch) = (levels[1].prev.width, levels[1].prev.height);
            let coarse = FlowField {
                width: cw,
                height: ch,
                u: vec![1.0; cw * ch],
                v: vec![-2.0; cw * ch],
            };
            let fine = upsample(&coarse, 100, 60, &levels[1]);
            let expect = (100.0 / cw as f32, -2.0 * 60.0 / ch as f32);
            assert!(fine.u.iter().all(|&u| (u - expect.0).abs() < 1e-5));
            assert!(fine.v.iter().all(|&v| (v - expect.1).abs() < 1e-5));
        }
        assert!(check_pyramid_params(17, 0.5).is_err());
        assert!(check_pyramid_params(3, 0.2).is_err());
        assert!(check_pyramid_params(3, f64::NAN).is_err());
        assert!(check_pyramid_params(3, 0.8).is_ok());
    }

    #[test]
    fn colour_coding() {
        let flow = FlowField {
            width: 4,
            height: 1,
            u: vec![0.0, 2.0, 0.0, f32::NAN],
            v: vec![0.0, 0.0, -2.0, 0.0],
        };
        let img = flow_to_color(&flow).unwrap();
        let PixelData::U8(d) = img.data() else {
            panic!()
        };
        assert_eq!(&d[0..3], &[255, 255, 255], "no motion is white");
        // Rightward motion at the largest length: pure red, the wheel's first colour.
        assert_eq!(&d[3..6], &[255, 0, 0]);
        assert_eq!(&d[9..12], &[0, 0, 0], "non-finite is black");
        let zeros = flow_to_color(&FlowField::zeros(0, 0)).unwrap();
        assert!(zeros.is_empty());
    }

    #[test]
    fn median_of_a_flow() {
        let mut flow = FlowField::zeros(9, 9);
        flow.u[40] = 100.0;
        flow.v[41] = -3.0;
        let m = median_flow(&flow, 3).unwrap();
        assert!(m.u.iter().chain(&m.v).all(|&x| x == 0.0));
        assert_eq!(median_flow(&flow, 1).unwrap(), flow);
    }
}
