//! `filter.lic` (line integral convolution) and `filter.edge_tangent_flow` (Kang, Lee & Chui).
//!
//! LIC: every output pixel is the mean of a texture sampled along the streamline of the vector
//! field through the pixel, `length` px forward and backward, in steps of `step` px (a box
//! kernel). Streamlines follow the unit field direction, integrated by the midpoint rule (RK2)
//! with bilinear sampling of field and texture; a streamline stops where it leaves the image or
//! meets a zero vector. Pixel `(x, y)` sits at coordinates `(x, y)`.
//!
//! ETF: tangents perpendicular to the Sobel gradient, smoothed iteratively by the weighted sum
//! over a disk of Kang, Lee & Chui (2007), then shown by a LIC of the flow over white noise.
//! Row bands run in parallel with fixed heights; outputs are bit-identical for any thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use rayon::prelude::*;

use super::border::BorderMode;
use super::grayscale::{LumaStandard, grayscale};
use super::sobel::sobel;

/// Rows per parallel band.
const BAND_ROWS: usize = 8;

/// Longest streamline half-length or ETF radius, px.
pub const MAX_LENGTH: f32 = 1000.0;

/// Smallest integration step, px.
pub const MIN_STEP: f32 = 0.05;

/// A single-channel f32 plane.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Row-major samples.
    pub data: Vec<f32>,
}

impl Plane {
    /// The samples of a single-channel image as f32, or an error naming `port`.
    pub fn from_image(image: &Image, port: &str) -> Result<Plane, String> {
        if image.channels() != Channels::Gray {
            return Err(format!(
                "`{port}` must be a single-channel image, got {}",
                image.channels().name()
            ));
        }
        let data = match image.data() {
            PixelData::U8(d) => d.iter().map(|&v| f32::from(v)).collect(),
            PixelData::U16(d) => d.iter().map(|&v| f32::from(v)).collect(),
            PixelData::F32(d) => d.clone(),
        };
        Ok(Plane {
            width: image.width(),
            height: image.height(),
            data,
        })
    }

    /// Bilinear sample at `(x, y)`, which must lie in `[0, w − 1] × [0, h − 1]`.
    #[inline]
    fn bilinear(&self, x: f32, y: f32) -> f32 {
        let (w, h) = (self.width, self.height);
        // Truncation is the floor for x, y ≥ 0 (`as` saturates negatives and NaN to 0) and,
        // unlike `floor`, needs no library call on baseline x86-64.
        let x0 = (x as usize).min(w - 1);
        let y0 = (y as usize).min(h - 1);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let d = &self.data;
        let top = d[y0 * w + x0] + (d[y0 * w + x1] - d[y0 * w + x0]) * fx;
        let bottom = d[y1 * w + x0] + (d[y1 * w + x1] - d[y1 * w + x0]) * fx;
        top + (bottom - top) * fy
    }

    fn into_image(self) -> Result<Image, String> {
        Image::from_f32(self.width, self.height, Channels::Gray, self.data)
            .map_err(|e| e.to_string())
    }
}

/// White noise uniform in [0, 1): splitmix64 of the seed and the pixel index (deterministic).
pub fn white_noise(width: usize, height: usize, seed: u64) -> Plane {
    let data = (0..width * height)
        .map(|i| {
            let mut z = seed
                .wrapping_add((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
                .wrapping_add(0x9E37_79B9_7F4A_7C15);
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect();
    Plane {
        width,
        height,
        data,
    }
}

/// LIC settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LicSettings {
    /// Streamline half-length, px.
    pub length: f32,
    /// Integration step, px.
    pub step: f32,
    /// Treat the field as orientations (v ≡ −v): each step keeps the previous direction's sign.
    pub orientation: bool,
}

/// Line integral convolution of `texture` along `(vx, vy)` (all the same size; see the module
/// docs).
pub fn lic(vx: &Plane, vy: &Plane, texture: &Plane, settings: LicSettings) -> Plane {
    let (w, h) = (texture.width, texture.height);
    let mut out = ocellus_engine::buffer::zeroed::<f32>(w * h);
    if w == 0 || h == 0 || vx.data.len() != w * h || vy.data.len() != w * h {
        return Plane {
            width: w,
            height: h,
            data: out,
        };
    }
    let steps = (settings.length / settings.step).floor() as usize;
    let hstep = settings.step;
    // The unit direction at p times `sign`; for orientation fields, aligned with `previous`
    // instead.
    let direction = |x: f32, y: f32, previous: (f32, f32), sign: f32| -> Option<(f32, f32)> {
        if !(0.0..=(w - 1) as f32).contains(&x) || !(0.0..=(h - 1) as f32).contains(&y) {
            return None;
        }
        let (mut dx, mut dy) = (vx.bilinear(x, y), vy.bilinear(x, y));
        let norm = (dx * dx + dy * dy).sqrt();
        if norm.is_nan() || norm <= 1e-12 || !norm.is_finite() {
            return None;
        }
        dx /= norm;
        dy /= norm;
        if settings.orientation {
            if dx * previous.0 + dy * previous.1 < 0.0 {
                dx = -dx;
                dy = -dy;
            }
        } else {
            dx *= sign;
            dy *= sign;
        }
        Some((dx, dy))
    };
    // Streamlines are serial chains of dependent steps; tracing LANES pixels in lockstep lets
    // their independent chains overlap. Each lane's arithmetic is the per-pixel one.
    const LANES: usize = 8;
    out.par_chunks_mut(BAND_ROWS * w)
        .enumerate()
        .for_each(|(band, rows)| {
            let base = band * BAND_ROWS * w;
            for (chunk, outs) in rows.chunks_mut(LANES).enumerate() {
                let lanes = outs.len();
                let first = base + chunk * LANES;
                let mut sum = [0f64; LANES];
                let mut count = [1u32; LANES];
                let mut origin = [(0f32, 0f32); LANES];
                let mut start = [None; LANES];
                for l in 0..lanes {
                    let i = first + l;
                    origin[l] = ((i % w) as f32, (i / w) as f32);
                    sum[l] = f64::from(texture.data[i]);
                    start[l] = direction(origin[l].0, origin[l].1, (0.0, 0.0), 1.0);
                }
                for sign in [1.0f32, -1.0] {
                    let mut alive = [false; LANES];
                    let mut at = origin;
                    let mut previous = [(0f32, 0f32); LANES];
                    for l in 0..lanes {
                        if let Some((sx, sy)) = start[l] {
                            alive[l] = true;
                            previous[l] = (sign * sx, sign * sy);
                        }
                    }
                    for _ in 0..steps {
                        let mut any = false;
                        for l in 0..lanes {
                            if !alive[l] {
                                continue;
                            }
                            let (x, y) = at[l];
                            // Midpoint rule on the unit direction field.
                            let step = direction(x, y, previous[l], sign).and_then(|d0| {
                                let (mx, my) = (x + 0.5 * hstep * d0.0, y + 0.5 * hstep * d0.1);
                                direction(mx, my, d0, sign)
                            });
                            let next = step.map(|d1| (d1, (x + hstep * d1.0, y + hstep * d1.1)));
                            match next {
                                Some((d1, (nx, ny)))
                                    if (0.0..=(w - 1) as f32).contains(&nx)
                                        && (0.0..=(h - 1) as f32).contains(&ny) =>
                                {
                                    at[l] = (nx, ny);
                                    previous[l] = d1;
                                    sum[l] += f64::from(texture.bilinear(nx, ny));
                                    count[l] += 1;
                                    any = true;
                                }
                                _ => alive[l] = false,
                            }
                        }
                        if !any {
                            break;
                        }
                    }
                }
                for (l, o) in outs.iter_mut().enumerate() {
                    *o = (sum[l] / f64::from(count[l])) as f32;
                }
            }
        });
    Plane {
        width: w,
        height: h,
        data: out,
    }
}

fn check_length(name: &str, v: f32, min: f32) -> Result<(), String> {
    if !v.is_finite() || v < min || v > MAX_LENGTH {
        return Err(format!(
            "`{name}` must be a finite number between {min} and {MAX_LENGTH}, got {v}"
        ));
    }
    Ok(())
}

params! {
    /// Parameters of `filter.lic`.
    pub struct LicParams {
        /// Streamline half-length, px, 0..=1000 (default 20): samples are taken up to this far
        /// forward and backward.
        length: f32 = 20.0 => [min = 0.0, max = 1000.0, unit = "px"],
        /// Integration step, px, 0.05..=1000 (default 0.5).
        step: f32 = 0.5 => [min = 0.05, max = 1000.0, unit = "px"],
        /// Seed of the white-noise texture used when `texture` is not connected (default 0).
        seed: u64 = 0,
        /// true: the field is an orientation field (v and −v alike; each step keeps the sign of
        /// the previous direction). Default false.
        orientation: bool = false,
    }
}

/// Line integral convolution (`filter.lic`). See [`lic`].
#[derive(Debug, Clone, PartialEq)]
pub struct Lic {
    settings: LicSettings,
    seed: u64,
}

impl Op for Lic {
    type Params = LicParams;
    const ID: &'static str = "filter.lic";
    const SUMMARY: &'static str =
        "Line integral convolution: smears a texture along the streamlines of a vector field.";
    const DOC: &'static str = r#"
Line integral convolution (B. Cabral and L. C. Leedom, "Imaging Vector Fields Using Line
Integral Convolution", SIGGRAPH 1993). Each output pixel is the mean (box kernel) of the
texture sampled along the streamline through the pixel: the pixel itself, then up to
⌊length/step⌋ points forward and as many backward, `step` px apart along the unit field
direction. Streamlines are integrated with the midpoint rule (RK2) on the bilinearly
interpolated, normalized field; textures are sampled bilinearly; pixel (x, y) sits at (x, y).
A streamline stops where it would leave [0, w − 1] × [0, h − 1] or meets a zero (or non-finite)
vector, so the mean is over fewer samples there; a zero field returns the texture. With
`orientation` the field is treated as sign-free (each step keeps the previous direction's
sign), for orientation fields such as edge tangents.

Inputs `vx`, `vy` and `texture` are single-channel images of the same size, any depth (read as
f32). Without `texture` the texture is white noise uniform in [0, 1) from `seed`. Output: f32
gray, within the texture's range. Row bands run in parallel; deterministic for any thread count.

Example:
    "flow": (op: "filter.lic", inputs: { "vx": "dx.image", "vy": "dy.image" }, params: (length: 15, seed: 7)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("vx", PortType::Image, "Field x component, single-channel."),
            PortSpec::new("vy", PortType::Image, "Field y component, single-channel."),
            PortSpec::new(
                "texture",
                PortType::Image,
                "Texture to convolve, single-channel (default: white noise from `seed`).",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The convolved texture, f32 gray.",
        )]
    }

    fn new(params: LicParams) -> Result<Self, String> {
        check_length("length", params.length, 0.0)?;
        check_length("step", params.step, MIN_STEP)?;
        Ok(Lic {
            settings: LicSettings {
                length: params.length,
                step: params.step,
                orientation: params.orientation,
            },
            seed: params.seed,
        })
    }
}

impl Operator for Lic {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let vx =
            Plane::from_image(inputs.image("vx")?, "vx").map_err(|e| OpError::input("vx", e))?;
        let vy =
            Plane::from_image(inputs.image("vy")?, "vy").map_err(|e| OpError::input("vy", e))?;
        if (vy.width, vy.height) != (vx.width, vx.height) {
            return Err(OpError::input(
                "vy",
                format!(
                    "size {}×{} differs from `vx` {}×{}",
                    vy.width, vy.height, vx.width, vx.height
                ),
            ));
        }
        let texture = match inputs.get("texture") {
            Some(_) => {
                let t = Plane::from_image(inputs.image("texture")?, "texture")
                    .map_err(|e| OpError::input("texture", e))?;
                if (t.width, t.height) != (vx.width, vx.height) {
                    return Err(OpError::input(
                        "texture",
                        format!(
                            "size {}×{} differs from the field's {}×{}",
                            t.width, t.height, vx.width, vx.height
                        ),
                    ));
                }
                t
            }
            None => white_noise(vx.width, vx.height, self.seed),
        };
        let out = lic(&vx, &vy, &texture, self.settings)
            .into_image()
            .map_err(OpError::failed)?;
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

// ---------------------------------------------------------------------------------------------
// Edge tangent flow

/// Edge tangent flow of a single-channel f32 plane: `(tx, ty)`, unit vectors (or zero where
/// the gradient and every weighted neighbour vanish).
pub fn edge_tangent_flow(gray: &Plane, radius: f32, iterations: usize) -> (Plane, Plane) {
    let (w, h) = (gray.width, gray.height);
    let empty = || Plane {
        width: w,
        height: h,
        data: vec![0.0; w * h],
    };
    if w == 0 || h == 0 {
        return (empty(), empty());
    }
    let image = match Image::from_f32(w, h, Channels::Gray, gray.data.clone()) {
        Ok(image) => image,
        Err(_) => return (empty(), empty()),
    };
    let derivative = |dx, dy| {
        sobel(&image, dx, dy, 3, 1.0, 0.0, BorderMode::Reflect101, 0.0)
            .as_f32()
            .map(<[f32]>::to_vec)
            .unwrap_or_else(|| vec![0.0; w * h])
    };
    let (gx, gy) = (derivative(1, 0), derivative(0, 1));
    let magnitude: Vec<f32> = gx.iter().zip(&gy).map(|(a, b)| a.hypot(*b)).collect();
    let top = magnitude.iter().copied().fold(0f32, f32::max);
    let g: Vec<f32> = if top > 0.0 {
        magnitude.iter().map(|m| m / top).collect()
    } else {
        vec![0.0; w * h]
    };
    // t0 ⟂ gradient, normalized.
    let mut t: Vec<(f32, f32)> = gx
        .iter()
        .zip(&gy)
        .zip(&magnitude)
        .map(|((&x, &y), &m)| if m > 0.0 { (-y / m, x / m) } else { (0.0, 0.0) })
        .collect();
    let r = radius.max(0.0);
    let reach = r.ceil() as isize;
    let disk: Vec<(isize, isize)> = (-reach..=reach)
        .flat_map(|dy| (-reach..=reach).map(move |dx| (dx, dy)))
        .filter(|&(dx, dy)| ((dx * dx + dy * dy) as f32).sqrt() < r || (dx, dy) == (0, 0))
        .collect();
    for _ in 0..iterations {
        let mut next = vec![(0f32, 0f32); w * h];
        next.par_chunks_mut(BAND_ROWS * w)
            .enumerate()
            .for_each(|(band, rows)| {
                for (i, o) in rows.iter_mut().enumerate() {
                    let (x, y) = ((i % w) as isize, (band * BAND_ROWS + i / w) as isize);
                    let c = y as usize * w + x as usize;
                    let tc = t[c];
                    let (mut sx, mut sy) = (0f32, 0f32);
                    for &(dx, dy) in &disk {
                        let (nx, ny) = (x + dx, y + dy);
                        if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                            continue;
                        }
                        let n = ny as usize * w + nx as usize;
                        let tn = t[n];
                        let dot = tc.0 * tn.0 + tc.1 * tn.1;
                        let wm = (g[n] - g[c] + 1.0) * 0.5;
                        // φ · w_d = sign(dot) · |dot| = dot.
                        let weight = wm * dot;
                        sx += weight * tn.0;
                        sy += weight * tn.1;
                    }
                    let norm = sx.hypot(sy);
                    *o = if norm > 0.0 && norm.is_finite() {
                        (sx / norm, sy / norm)
                    } else {
                        tc
                    };
                }
            });
        t = next;
    }
    let (tx, ty): (Vec<f32>, Vec<f32>) = t.into_iter().unzip();
    (
        Plane {
            width: w,
            height: h,
            data: tx,
        },
        Plane {
            width: w,
            height: h,
            data: ty,
        },
    )
}

params! {
    /// Parameters of `filter.edge_tangent_flow`.
    pub struct EtfParams {
        /// Radius of the smoothing disk, px, 0..=1000 (default 5).
        radius: f32 = 5.0 => [min = 0.0, max = 1000.0, unit = "px"],
        /// Smoothing iterations, 0..=100 (default 3).
        iterations: u32 = 3 => [min = 0, max = 100],
        /// Seed of the noise of the visualization (default 0).
        seed: u64 = 0,
        /// Streamline half-length of the visualization's LIC, px, 0..=1000 (default 10).
        lic_length: f32 = 10.0 => [min = 0.0, max = 1000.0, unit = "px"],
    }
}

/// Edge tangent flow (`filter.edge_tangent_flow`). See [`edge_tangent_flow`].
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeTangentFlow {
    radius: f32,
    iterations: usize,
    seed: u64,
    lic_length: f32,
}

impl Op for EdgeTangentFlow {
    type Params = EtfParams;
    const ID: &'static str = "filter.edge_tangent_flow";
    const SUMMARY: &'static str =
        "Edge tangent flow: smooth unit tangents along image edges (Kang, Lee & Chui).";
    const DOC: &'static str = r#"
Edge tangent flow (H. Kang, S. Lee and C. K. Chui, "Coherent Line Drawing", NPAR 2007). The
image is made gray (BT.601 for colour, alpha ignored) and read as f32; the Sobel 3×3 gradient
(reflect-101 border) gives the magnitude ĝ normalized to [0, 1] by its maximum and the initial
tangent t⁰, the gradient turned 90° counter-clockwise ((−g_y, g_x)) and normalized. Each of
`iterations` steps replaces t(x) by the normalized sum over the disk ‖y − x‖ < `radius` of
φ(x, y)·t(y)·w_m·w_d, with w_m = (ĝ(y) − ĝ(x) + 1)/2, w_d = |t(x)·t(y)| and
φ = sign(t(x)·t(y)), the full disk (not the separable approximation). Where the gradient is zero
the tangent starts at zero and stays zero unless neighbours pull it (w_d = 0 there, so flat
regions keep zero tangents). Outputs `tx`, `ty` (f32, unit length where non-zero) and
`visualization`: a LIC of the flow (orientation mode, step 0.5 px, half-length `lic_length`)
over white noise from `seed`, as u8 gray (value · 255, rounded).

Example:
    "etf": (op: "filter.edge_tangent_flow", inputs: { "image": "photo.image" }, params: (radius: 5, iterations: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image, any pixel format (made gray).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("tx", PortType::Image, "Tangent x component, f32 gray."),
            PortSpec::new("ty", PortType::Image, "Tangent y component, f32 gray."),
            PortSpec::new(
                "visualization",
                PortType::Image,
                "LIC of the flow over white noise, u8 gray.",
            ),
        ]
    }

    fn new(params: EtfParams) -> Result<Self, String> {
        check_length("radius", params.radius, 0.0)?;
        check_length("lic_length", params.lic_length, 0.0)?;
        if params.iterations > 100 {
            return Err(format!(
                "`iterations` must be at most 100, got {}",
                params.iterations
            ));
        }
        Ok(EdgeTangentFlow {
            radius: params.radius,
            iterations: params.iterations as usize,
            seed: params.seed,
            lic_length: params.lic_length,
        })
    }
}

impl Operator for EdgeTangentFlow {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let gray = grayscale(image, LumaStandard::Bt601)
            .map_err(|e| OpError::failed(format!("building the gray image: {e}")))?;
        let plane = Plane::from_image(&gray, "image").map_err(|e| OpError::input("image", e))?;
        let (tx, ty) = edge_tangent_flow(&plane, self.radius, self.iterations);
        let noise = white_noise(plane.width, plane.height, self.seed);
        let settings = LicSettings {
            length: self.lic_length,
            step: 0.5,
            orientation: true,
        };
        let shown = lic(&tx, &ty, &noise, settings);
        let bytes = shown
            .data
            .iter()
            .map(|&v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
            .collect();
        let visualization = Image::from_u8(plane.width, plane.height, Channels::Gray, bytes)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with(
                "tx",
                Value::image(tx.into_image().map_err(OpError::failed)?),
            )
            .with(
                "ty",
                Value::image(ty.into_image().map_err(OpError::failed)?),
            )
            .with("visualization", Value::image(visualization)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn constant(w: usize, h: usize, v: f32) -> Plane {
        Plane {
            width: w,
            height: h,
            data: vec![v; w * h],
        }
    }

    fn settings(length: f32, step: f32) -> LicSettings {
        LicSettings {
            length,
            step,
            orientation: false,
        }
    }

    #[test]
    fn horizontal_field_is_a_horizontal_box_filter() {
        let (w, h) = (40, 7);
        let noise = white_noise(w, h, 3);
        let l = 5;
        for (vx, vy) in [(1.0, 0.0), (-2.5, 0.0)] {
            let out = lic(
                &constant(w, h, vx),
                &constant(w, h, vy),
                &noise,
                settings(l as f32, 1.0),
            );
            for y in 0..h {
                for x in l..w - l {
                    let mean: f32 = noise.data[y * w + x - l..=y * w + x + l]
                        .iter()
                        .sum::<f32>()
                        / (2 * l + 1) as f32;
                    assert!(
                        (out.data[y * w + x] - mean).abs() < 1e-5,
                        "({x}, {y}) {} {mean}",
                        out.data[y * w + x]
                    );
                }
            }
        }
        // A vertical field filters columns; step 0.5 samples half-way points bilinearly.
        let out = lic(
            &constant(w, h, 0.0),
            &constant(w, h, 1.0),
            &noise,
            settings(0.5, 0.5),
        );
        let (x, y) = (10, 3);
        let t = &noise.data;
        let expected = (t[y * w + x]
            + 0.5 * (t[(y - 1) * w + x] + t[y * w + x])
            + 0.5 * (t[(y + 1) * w + x] + t[y * w + x]))
            / 3.0;
        assert!((out.data[y * w + x] - expected).abs() < 1e-6);
    }

    #[test]
    fn zero_field_returns_the_texture_and_outputs_stay_in_range() {
        let (w, h) = (23, 17);
        let noise = white_noise(w, h, 9);
        let zero = constant(w, h, 0.0);
        assert_eq!(lic(&zero, &zero, &noise, settings(20.0, 0.5)), noise);
        // A swirl: output within the texture's range, deterministic, thread-independent.
        let (mut vx, mut vy) = (zero.clone(), zero.clone());
        for y in 0..h {
            for x in 0..w {
                vx.data[y * w + x] = -(y as f32 - 8.0);
                vy.data[y * w + x] = x as f32 - 11.0;
            }
        }
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let run = || lic(&vx, &vy, &noise, settings(7.0, 0.5));
        let out = pool(1).install(run);
        assert_eq!(out, pool(3).install(run));
        let (lo, hi) = noise
            .data
            .iter()
            .fold((1f32, 0f32), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(out.data.iter().all(|&v| v >= lo - 1e-6 && v <= hi + 1e-6));
        // Noise is uniform in [0, 1) and changes with the seed.
        assert!(noise.data.iter().all(|&v| (0.0..1.0).contains(&v)));
        assert_ne!(white_noise(w, h, 10), noise);
        let tiny = white_noise(1, 1, 0);
        assert_eq!(
            lic(
                &constant(1, 1, 1.0),
                &constant(1, 1, 0.0),
                &tiny,
                settings(5.0, 0.5)
            ),
            tiny
        );
        let empty = white_noise(0, 0, 0);
        assert_eq!(
            lic(&empty, &empty, &empty, settings(5.0, 0.5)).data.len(),
            0
        );
    }

    #[test]
    fn etf_follows_a_step_edge() {
        // A vertical step edge: tangents along y; a diagonal edge: along the diagonal.
        let (w, h) = (24, 20);
        let mut img = constant(w, h, 0.0);
        for y in 0..h {
            for x in 12..w {
                img.data[y * w + x] = 200.0;
            }
        }
        let (tx, ty) = edge_tangent_flow(&img, 5.0, 3);
        for y in 0..h {
            for x in 11..13 {
                let i = y * w + x;
                assert!(
                    tx.data[i].abs() < 1e-5 && (ty.data[i].abs() - 1.0).abs() < 1e-5,
                    "({x}, {y})"
                );
            }
        }
        let mut diag = constant(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                if x > y {
                    diag.data[y * w + x] = 100.0;
                }
            }
        }
        let (tx, ty) = edge_tangent_flow(&diag, 3.0, 2);
        let s = std::f32::consts::FRAC_1_SQRT_2;
        for k in 6..14 {
            let i = k * w + k;
            assert!(
                (tx.data[i].abs() - s).abs() < 1e-3,
                "{k} {} {}",
                tx.data[i],
                ty.data[i]
            );
            assert!((tx.data[i] * ty.data[i]) > 0.0, "{k}: along the diagonal");
            // Unit length where non-zero.
            assert!((tx.data[i].hypot(ty.data[i]) - 1.0).abs() < 1e-5);
        }
        // Flat image: zero tangents; deterministic across thread counts.
        let (fx, _) = edge_tangent_flow(&constant(5, 4, 7.0), 5.0, 3);
        assert!(fx.data.iter().all(|&v| v == 0.0));
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let run = || edge_tangent_flow(&diag, 4.0, 3);
        assert_eq!(pool(1).install(run), pool(2).install(run));
    }

    #[test]
    fn etf_tangents_are_unit_or_zero() {
        let noise = white_noise(31, 29, 5);
        let (tx, ty) = edge_tangent_flow(&noise, 2.5, 2);
        for (x, y) in tx.data.iter().zip(&ty.data) {
            let n = x.hypot(*y);
            assert!(n == 0.0 || (n - 1.0).abs() < 1e-5, "{n}");
        }
    }

    fn run(
        op: &dyn Operator,
        specs: &[PortSpec],
        values: &[Option<Value>],
    ) -> Result<Outputs, OpError> {
        let ctx = RunContext {
            node: "f".into(),
            threads: 1,
            element: None,
        };
        op.run(&ctx, &Inputs::new(specs, values))
    }

    fn image_of(p: &Plane) -> Value {
        Value::image(p.clone().into_image().unwrap())
    }

    #[test]
    fn operators_run_and_check() {
        let (w, h) = (16, 12);
        let op = Lic::new(LicParams::default()).unwrap();
        let specs = Lic::inputs();
        let vx = constant(w, h, 1.0);
        let vy = constant(w, h, 0.0);
        let mut out = run(
            &op,
            &specs,
            &[Some(image_of(&vx)), Some(image_of(&vy)), None],
        )
        .unwrap();
        let expected = lic(&vx, &vy, &white_noise(w, h, 0), settings(20.0, 0.5));
        match out.take("image") {
            Some(Value::Image(got)) => assert_eq!(got.as_f32().unwrap(), &expected.data[..]),
            _ => panic!("expected an image"),
        }
        let small = constant(3, 3, 1.0);
        let err = run(
            &op,
            &specs,
            &[Some(image_of(&vx)), Some(image_of(&small)), None],
        )
        .unwrap_err();
        assert!(err.to_string().contains("differs"), "{err}");
        let rgb = Value::image(Image::from_u8(w, h, Channels::Rgb, vec![0; w * h * 3]).unwrap());
        let err = run(
            &op,
            &specs,
            &[Some(image_of(&vx)), Some(image_of(&vy)), Some(rgb.clone())],
        )
        .unwrap_err();
        assert!(err.to_string().contains("single-channel"), "{err}");
        assert!(
            Lic::new(LicParams {
                step: 0.0,
                ..LicParams::default()
            })
            .is_err()
        );
        assert!(
            Lic::new(LicParams {
                length: f32::NAN,
                ..LicParams::default()
            })
            .is_err()
        );

        let etf = EdgeTangentFlow::new(EtfParams::default()).unwrap();
        let specs = EdgeTangentFlow::inputs();
        let mut out = run(&etf, &specs, &[Some(rgb)]).unwrap();
        for port in ["tx", "ty", "visualization"] {
            match out.take(port) {
                Some(Value::Image(got)) => assert_eq!((got.width(), got.height()), (w, h)),
                _ => panic!("expected {port}"),
            }
        }
        assert!(
            EdgeTangentFlow::new(EtfParams {
                radius: f32::INFINITY,
                ..EtfParams::default()
            })
            .is_err()
        );
        assert!(
            EdgeTangentFlow::new(EtfParams {
                iterations: 101,
                ..EtfParams::default()
            })
            .is_err()
        );
    }
}
