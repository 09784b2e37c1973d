//! Gray f32 planes (0–255 scale) of any input image, shared by the motion operators.
//!
//! Conversion: u8 as is; u16 `v / 257`; f32 `v · 255` (NaN read as 0); RGB / RGBA by BT.601
//! luma `0.299 R + 0.587 G + 0.114 B` after the per-sample conversion (alpha ignored).

use ocellus_engine::value::{Channels, Image, PixelData};

use crate::filter::border::BorderMode;
use crate::filter::pyramid::pyr_down;
use crate::filter::sobel::scharr;

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
        let x0 = (xc.floor() as usize).min(w - 1);
        let y0 = (yc.floor() as usize).min(h - 1);
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

fn plane_of(image: &Image) -> Plane {
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

/// Scharr gradients `(∂x, ∂y)` of a plane, normalised to gray levels per pixel (Scharr / 32),
/// reflect-101 border.
pub fn gradients(plane: &Plane) -> Result<(Plane, Plane), String> {
    let image = plane.to_image()?;
    let gx = scharr(&image, true, 1.0 / 32.0, 0.0, BorderMode::Reflect101, 0.0);
    let gy = scharr(&image, false, 1.0 / 32.0, 0.0, BorderMode::Reflect101, 0.0);
    Ok((plane_of(&gx), plane_of(&gy)))
}
