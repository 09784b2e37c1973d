//! Gray f32 planes (0–255 scale) of any input image, shared by the motion operators.
//!
//! Conversion: u8 as is; u16 `v / 257`; f32 `v · 255` (NaN read as 0); RGB / RGBA by BT.601
//! luma `0.299 R + 0.587 G + 0.114 B` after the per-sample conversion (alpha ignored).

use ocellus_engine::value::{Channels, Image, PixelData};
use rayon::prelude::*;

use crate::filter::pyramid::pyr_down;
#[cfg(test)]
use crate::filter::{border::BorderMode, sobel::scharr};

/// A gray f32 plane, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `width × height` samples.
    pub data: Vec<f32>,
}

impl Plane {
    /// The plane as a gray f32 image.
    pub fn to_image(&self) -> Result<Image, String> {
        Image::from_f32(self.width, self.height, Channels::Gray, self.data.clone())
            .map_err(|e| e.to_string())
    }

    /// Bilinear sample at (x, y), coordinates clamped to the image (replicated border).
    #[inline]
    pub fn bilinear(&self, x: f32, y: f32) -> f32 {
        let (w, h) = (self.width, self.height);
        let xc = x.clamp(0.0, (w - 1) as f32);
        let yc = y.clamp(0.0, (h - 1) as f32);
        // `xc` and `yc` are non-negative (or NaN, which converts to 0 either way), so truncation
        // is the floor, without the libm call `floor` is on baseline x86-64 (as in
        // `filter::flow`); through `i64` it is one conversion instruction, where a direct
        // float-to-`usize` conversion adds a second conversion and a select for values ≥ 2⁶³.
        let x0 = (xc as i64 as usize).min(w - 1);
        let y0 = (yc as i64 as usize).min(h - 1);
        let x1 = (x0 + 1).min(w - 1);
        let y1 = (y0 + 1).min(h - 1);
        let fx = xc - x0 as f32;
        let fy = yc - y0 as f32;
        let r0 = &self.data[y0 * w..];
        let r1 = &self.data[y1 * w..];
        let top = r0[x0] + (r0[x1] - r0[x0]) * fx;
        let bottom = r1[x0] + (r1[x1] - r1[x0]) * fx;
        top + (bottom - top) * fy
    }
}

fn from_image(image: &Image) -> Plane {
    let c = image.channels().count();
    let samples: Vec<f32> = match image.data() {
        PixelData::U8(v) => v.iter().map(|&s| f32::from(s)).collect(),
        PixelData::U16(v) => v.iter().map(|&s| f32::from(s) / 257.0).collect(),
        PixelData::F32(v) => v
            .iter()
            .map(|&s| if s.is_nan() { 0.0 } else { s * 255.0 })
            .collect(),
    };
    let data = if c == 1 {
        samples
    } else {
        samples
            .chunks_exact(c)
            .map(|p| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
            .collect()
    };
    Plane {
        width: image.width(),
        height: image.height(),
        data,
    }
}

/// Gray f32 plane (0–255 scale) of any image.
pub fn gray_f32(image: &Image) -> Plane {
    from_image(image)
}

/// The samples of an image as a plane: f32 gray images as they are (no rescaling), other
/// formats through [`gray_f32`].
pub(crate) fn plane_of(image: &Image) -> Plane {
    match image.data() {
        PixelData::F32(v) => Plane {
            width: image.width(),
            height: image.height(),
            data: v.clone(),
        },
        _ => from_image(image),
    }
}

/// Gaussian pyramid (OpenCV `pyrDown` steps) of a plane: at most `levels + 1` planes, level 0
/// the plane itself; stops before a level would be smaller than `min_side` px.
pub fn pyramid(plane: &Plane, levels: usize, min_side: usize) -> Result<Vec<Plane>, String> {
    let mut out = vec![plane.clone()];
    while out.len() <= levels {
        let Some(last) = out.last() else { break };
        if last.width.div_ceil(2) < min_side || last.height.div_ceil(2) < min_side {
            break;
        }
        let down = pyr_down(&last.to_image()?)?;
        out.push(plane_of(&down));
    }
    Ok(out)
}

/// Rows per parallel band of [`gradients`].
const BAND_ROWS: usize = 32;

/// Reflect-101 index of `i` (may be −1 or `n`) in `0..n`.
#[inline]
fn reflect101(i: isize, n: usize) -> usize {
    if n == 1 {
        0
    } else if i < 0 {
        1
    } else if i as usize >= n {
        n - 2
    } else {
        i as usize
    }
}

/// Scharr gradients `(∂x, ∂y)` of a plane, normalised to gray levels per pixel (Scharr / 32),
/// reflect-101 border (`cv::Scharr` with scale 1/32). Rows are processed in fixed bands in
/// parallel; each output sample depends only on its 3×3 neighbourhood.
pub fn gradients(plane: &Plane) -> Result<(Plane, Plane), String> {
    let (w, h) = (plane.width, plane.height);
    let mut gx = vec![0.0f32; w * h];
    let mut gy = vec![0.0f32; w * h];
    if w > 0 && h > 0 {
        let src = &plane.data;
        gx.par_chunks_mut(BAND_ROWS * w)
            .zip(gy.par_chunks_mut(BAND_ROWS * w))
            .enumerate()
            .for_each(|(band, (bx, by))| {
                // Padded vertical smoothing (3, 10, 3) and difference rows.
                let mut smooth = vec![0.0f32; w + 2];
                let mut diff = vec![0.0f32; w + 2];
                for (r, (ox, oy)) in bx
                    .chunks_exact_mut(w)
                    .zip(by.chunks_exact_mut(w))
                    .enumerate()
                {
                    let y = band * BAND_ROWS + r;
                    let up = &src[reflect101(y as isize - 1, h) * w..][..w];
                    let mid = &src[y * w..][..w];
                    let down = &src[reflect101(y as isize + 1, h) * w..][..w];
                    for x in 0..w {
                        smooth[x + 1] = 3.0 * (up[x] + down[x]) + 10.0 * mid[x];
                        diff[x + 1] = down[x] - up[x];
                    }
                    let (l, rr) = (reflect101(-1, w), reflect101(w as isize, w));
                    smooth[0] = smooth[l + 1];
                    diff[0] = diff[l + 1];
                    smooth[w + 1] = smooth[rr + 1];
                    diff[w + 1] = diff[rr + 1];
                    let k = 1.0 / 32.0;
                    for x in 0..w {
                        ox[x] = (smooth[x + 2] - smooth[x]) * k;
                        oy[x] = (3.0 * (diff[x] + diff[x + 2]) + 10.0 * diff[x + 1]) * k;
                    }
                }
            });
    }
    Ok((
        Plane {
            width: w,
            height: h,
            data: gx,
        },
        Plane {
            width: w,
            height: h,
            data: gy,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::random_u8;
    use ocellus_engine::value::Channels;

    /// The sampling formula with `floor`, as it was written before truncation replaced it.
    fn bilinear_with_floor(plane: &Plane, x: f32, y: f32) -> f32 {
        let (w, h) = (plane.width, plane.height);
        let xc = x.clamp(0.0, (w - 1) as f32);
        let yc = y.clamp(0.0, (h - 1) as f32);
        let x0 = (xc.floor() as usize).min(w - 1);
        let y0 = (yc.floor() as usize).min(h - 1);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (xc - x0 as f32, yc - y0 as f32);
        let (r0, r1) = (&plane.data[y0 * w..], &plane.data[y1 * w..]);
        let top = r0[x0] + (r0[x1] - r0[x0]) * fx;
        let bottom = r1[x0] + (r1[x1] - r1[x0]) * fx;
        top + (bottom - top) * fy
    }

    #[test]
    fn bilinear_is_bit_identical_to_the_floor_formula() {
        let specials = [
            f32::NAN,
            -0.0,
            0.0,
            -1.5,
            f32::NEG_INFINITY,
            f32::INFINITY,
            1e30,
            0.999_999_9,
        ];
        for (w, h) in [(1, 1), (2, 3), (37, 70), (5, 1)] {
            let plane = gray_f32(&random_u8(w, h, Channels::Gray, 3));
            let mut coordinates: Vec<f32> = specials.to_vec();
            for k in 0..=(8 * w.max(h)) {
                let t = k as f32 / 8.0;
                coordinates.extend([t, t - 1.0 / 1024.0, t + 1.0 / 1024.0]);
            }
            for &x in &coordinates {
                for &y in coordinates.iter().step_by(5) {
                    let (ours, reference) =
                        (plane.bilinear(x, y), bilinear_with_floor(&plane, x, y));
                    assert_eq!(ours.to_bits(), reference.to_bits(), "{w}x{h} at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn gradients_match_filter_scharr() {
        for (w, h) in [(1, 1), (2, 3), (37, 70), (5, 1)] {
            let img = random_u8(w, h, Channels::Gray, 9);
            let plane = gray_f32(&img);
            let (gx, gy) = gradients(&plane).unwrap();
            let image = plane.to_image().unwrap();
            for (ours, along_x) in [(&gx, true), (&gy, false)] {
                let theirs = plane_of(&scharr(
                    &image,
                    along_x,
                    1.0 / 32.0,
                    0.0,
                    BorderMode::Reflect101,
                    0.0,
                ));
                for (a, b) in ours.data.iter().zip(&theirs.data) {
                    assert!((a - b).abs() < 1e-3, "{w}x{h}: {a} vs {b}");
                }
            }
        }
    }
}
