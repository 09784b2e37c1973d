//! Texture sampling for the renderers: address modes, nearest and bilinear filtering, a
//! box-filtered mip chain with trilinear filtering (Williams 1983, "Pyramidal Parametrics"), and
//! anisotropic filtering by several trilinear probes along the footprint's major axis (the
//! `EXT_texture_filter_anisotropic` scheme).
//!
//! Coordinates follow the OBJ/OpenGL convention of [`Mesh`](ocellus_engine::value::Mesh) uvs:
//! `(0, 0)` is the image's bottom-left corner, `v` points up, and texel `(x, y)` (row `y` from
//! the top) has its centre at `u = (x + ½)/W`, `v = 1 − (y + ½)/H`.

use ocellus_engine::value::{PixelData, Texture, TextureFilter, TextureWrap};

/// One level of a mip chain: RGBA texels, row-major from the top.
#[derive(Debug, Clone, PartialEq)]
pub struct MipLevel {
    /// Width, texels.
    pub width: usize,
    /// Height, texels.
    pub height: usize,
    /// Texels, `width × height`.
    pub texels: Vec<[f32; 4]>,
}

/// A texture ready for sampling: RGBA f32 texels with their mip chain and the sampler state of
/// the [`Texture`] it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct TextureSampler {
    /// Level 0 (the image) first, then each level half the size of the one before, down to 1×1.
    pub levels: Vec<MipLevel>,
    wrap: TextureWrap,
    filter: TextureFilter,
    border: [f32; 4],
    max_anisotropy: u32,
    uv_scale: [f32; 2],
}

impl TextureSampler {
    /// Converts the texture's image to RGBA f32 (u8 read as `v/255`, u16 as `v/65535`; gray
    /// becomes `(g, g, g, 1)`, RGB gets alpha 1) and builds the mip chain. Each coarser level
    /// averages the finer one over its exact footprint (odd sizes give fractional weights), so
    /// every level has the image's mean.
    pub fn new(texture: &Texture) -> Result<TextureSampler, String> {
        let image = &texture.image;
        let (w, h, c) = (image.width(), image.height(), image.channels().count());
        if w == 0 || h == 0 {
            return Err(format!("texture image is empty ({w}×{h})"));
        }
        if !(1..=16).contains(&texture.max_anisotropy) {
            return Err(format!(
                "texture `max_anisotropy` must be 1..=16, got {}",
                texture.max_anisotropy
            ));
        }
        if !texture
            .uv_scale
            .iter()
            .chain(&texture.border)
            .all(|v| v.is_finite())
        {
            return Err("texture `uv_scale` and `border` must be finite".into());
        }
        let sample = |i: usize| -> f32 {
            match image.data() {
                PixelData::U8(v) => f32::from(v[i]) / 255.0,
                PixelData::U16(v) => f32::from(v[i]) / 65535.0,
                PixelData::F32(v) => v[i],
            }
        };
        let mut texels = Vec::with_capacity(w * h);
        for p in 0..w * h {
            let s = |k: usize| sample(p * c + k);
            texels.push(match c {
                1 => [s(0), s(0), s(0), 1.0],
                3 => [s(0), s(1), s(2), 1.0],
                _ => [s(0), s(1), s(2), s(3)],
            });
        }
        if texels.iter().flatten().any(|v| !v.is_finite()) {
            return Err("texture holds non-finite texels".into());
        }
        let mut levels = vec![MipLevel {
            width: w,
            height: h,
            texels,
        }];
        while let Some(last) = levels.last() {
            if last.width == 1 && last.height == 1 {
                break;
            }
            let next = downsample(last);
            levels.push(next);
        }
        Ok(TextureSampler {
            levels,
            wrap: texture.wrap,
            filter: texture.filter,
            border: texture.border,
            max_anisotropy: texture.max_anisotropy,
            uv_scale: texture.uv_scale,
        })
    }

    /// Texel `(x, y)` of `level` after the address mode (may be the border colour).
    pub fn texel(&self, level: usize, x: i64, y: i64) -> [f32; 4] {
        let l = &self.levels[level.min(self.levels.len() - 1)];
        match (
            address(x, l.width, self.wrap),
            address(y, l.height, self.wrap),
        ) {
            (Some(x), Some(y)) => l.texels[y * l.width + x],
            _ => self.border,
        }
    }

    fn nearest(&self, level: usize, uv: [f32; 2]) -> [f32; 4] {
        let l = &self.levels[level];
        let x = (f64::from(uv[0]) * l.width as f64).floor();
        let y = ((1.0 - f64::from(uv[1])) * l.height as f64).floor();
        self.texel(level, clamp_i64(x), clamp_i64(y))
    }

    fn bilinear(&self, level: usize, uv: [f32; 2]) -> [f32; 4] {
        let l = &self.levels[level];
        let fx = f64::from(uv[0]) * l.width as f64 - 0.5;
        let fy = (1.0 - f64::from(uv[1])) * l.height as f64 - 0.5;
        let (x0, y0) = (fx.floor(), fy.floor());
        let (ax, ay) = ((fx - x0) as f32, (fy - y0) as f32);
        let (x0, y0) = (clamp_i64(x0), clamp_i64(y0));
        let t00 = self.texel(level, x0, y0);
        let t10 = self.texel(level, x0.saturating_add(1), y0);
        let t01 = self.texel(level, x0, y0.saturating_add(1));
        let t11 = self.texel(level, x0.saturating_add(1), y0.saturating_add(1));
        std::array::from_fn(|k| {
            let top = t00[k] + (t10[k] - t00[k]) * ax;
            let bottom = t01[k] + (t11[k] - t01[k]) * ax;
            top + (bottom - top) * ay
        })
    }

    /// Trilinear lookup at a level of detail (`lod` 0 is the image; fractional levels blend
    /// the two nearest, clamped to the chain).
    pub fn sample_lod(&self, uv: [f32; 2], lod: f32) -> [f32; 4] {
        let uv = self.scaled(uv);
        self.trilinear(uv, lod)
    }

    fn trilinear(&self, uv: [f32; 2], lod: f32) -> [f32; 4] {
        let top = (self.levels.len() - 1) as f32;
        let lod = if lod.is_nan() {
            0.0
        } else {
            lod.clamp(0.0, top)
        };
        let l0 = lod.floor() as usize;
        let t = lod - l0 as f32;
        let a = self.bilinear(l0, uv);
        if t == 0.0 || l0 + 1 >= self.levels.len() {
            return a;
        }
        let b = self.bilinear(l0 + 1, uv);
        std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t)
    }

    fn scaled(&self, uv: [f32; 2]) -> [f32; 2] {
        [uv[0] * self.uv_scale[0], uv[1] * self.uv_scale[1]]
    }

    /// A point sample at `uv` from level 0: nearest for [`TextureFilter::Nearest`], bilinear
    /// otherwise (no footprint is known, so no mip level is chosen).
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 4] {
        self.point(0, self.scaled(uv))
    }

    fn point(&self, level: usize, uv: [f32; 2]) -> [f32; 4] {
        match self.filter {
            TextureFilter::Nearest => self.nearest(level, uv),
            _ => self.bilinear(level, uv),
        }
    }

    /// A filtered sample at `uv` whose screen-space footprint has the uv derivatives
    /// `duv_dx`, `duv_dy` (per pixel, before `uv_scale`). Nearest and bilinear read level 0;
    /// trilinear picks `λ = log₂ ρ` with `ρ` the longer footprint axis in texels; anisotropic
    /// takes `N = min(⌈major/minor⌉, max_anisotropy)` trilinear probes spread evenly along the
    /// major axis at `λ = log₂(major/N)` and averages them.
    pub fn sample_grad(&self, uv: [f32; 2], duv_dx: [f32; 2], duv_dy: [f32; 2]) -> [f32; 4] {
        let uv = self.scaled(uv);
        let (w, h) = (self.levels[0].width as f32, self.levels[0].height as f32);
        let tx = [
            duv_dx[0] * self.uv_scale[0] * w,
            duv_dx[1] * self.uv_scale[1] * h,
        ];
        let ty = [
            duv_dy[0] * self.uv_scale[0] * w,
            duv_dy[1] * self.uv_scale[1] * h,
        ];
        let (lx, ly) = (tx[0].hypot(tx[1]), ty[0].hypot(ty[1]));
        match self.filter {
            TextureFilter::Nearest => self.nearest(0, uv),
            TextureFilter::Bilinear => self.bilinear(0, uv),
            TextureFilter::Trilinear => self.trilinear(uv, lx.max(ly).max(1e-30).log2()),
            TextureFilter::Anisotropic => {
                let (major, minor, axis) = if lx >= ly {
                    (
                        lx,
                        ly,
                        [duv_dx[0] * self.uv_scale[0], duv_dx[1] * self.uv_scale[1]],
                    )
                } else {
                    (
                        ly,
                        lx,
                        [duv_dy[0] * self.uv_scale[0], duv_dy[1] * self.uv_scale[1]],
                    )
                };
                if !(major.is_finite() && major > 0.0) {
                    return self.trilinear(uv, 0.0);
                }
                let ratio = (major / minor.max(1e-30)).ceil();
                let n = if ratio.is_finite() {
                    (ratio as u32).clamp(1, self.max_anisotropy)
                } else {
                    self.max_anisotropy
                };
                let lod = (major / n as f32).max(1e-30).log2();
                let mut sum = [0.0f32; 4];
                for i in 0..n {
                    let s = (i as f32 + 0.5) / n as f32 - 0.5;
                    let p = [uv[0] + s * axis[0], uv[1] + s * axis[1]];
                    let t = self.trilinear(p, lod);
                    for k in 0..4 {
                        sum[k] += t[k];
                    }
                }
                sum.map(|v| v / n as f32)
            }
        }
    }

    /// The equirectangular (latitude–longitude) lookup for a world direction: longitude
    /// `φ = atan2(x, −z)` gives `u = ½ + φ/2π` (the image centre column looks along −z), the
    /// polar angle `θ` from +y gives `v = 1 − θ/π` (the top row is +y). Filtered as
    /// [`TextureSampler::sample`].
    pub fn sample_direction(&self, dir: [f64; 3]) -> [f32; 4] {
        let n = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
        if !(n > 0.0 && n.is_finite()) {
            return self.sample([0.5, 0.5]);
        }
        let d = dir.map(|c| c / n);
        let phi = d[0].atan2(-d[2]);
        let theta = d[1].clamp(-1.0, 1.0).acos();
        let u = 0.5 + phi / std::f64::consts::TAU;
        let v = 1.0 - theta / std::f64::consts::PI;
        // The uv scale is for tiling surfaces; an environment map is read unscaled.
        self.point(0, [u as f32, v as f32])
    }
}

fn clamp_i64(v: f64) -> i64 {
    if v.is_nan() {
        0
    } else {
        v.clamp(-(1i64 << 52) as f64, (1i64 << 52) as f64) as i64
    }
}

/// The texel index an address mode maps `i` to, or `None` for the border.
fn address(i: i64, n: usize, wrap: TextureWrap) -> Option<usize> {
    let n = n as i64;
    let j = match wrap {
        TextureWrap::Repeat => i.rem_euclid(n),
        TextureWrap::MirroredRepeat => {
            let k = i.rem_euclid(2 * n);
            if k < n { k } else { 2 * n - 1 - k }
        }
        TextureWrap::ClampToEdge => i.clamp(0, n - 1),
        TextureWrap::ClampToBorder => {
            if !(0..n).contains(&i) {
                return None;
            }
            i
        }
    };
    Some(j as usize)
}

/// Weights of the source texels that the destination texel `d` of an `m`-texel axis covers
/// when `n` source texels shrink to `m`: its footprint is `[d·n/m, (d+1)·n/m)`.
fn footprint(d: usize, n: usize, m: usize) -> Vec<(usize, f64)> {
    let scale = n as f64 / m as f64;
    let (a, b) = (d as f64 * scale, (d + 1) as f64 * scale);
    let mut out = Vec::with_capacity(scale.ceil() as usize + 1);
    let mut s = a.floor() as usize;
    while (s as f64) < b && s < n {
        let lo = (s as f64).max(a);
        let hi = ((s + 1) as f64).min(b);
        if hi > lo {
            out.push((s, (hi - lo) / scale));
        }
        s += 1;
    }
    out
}

/// The next mip level: half the size on each axis (at least 1), each texel the exact average
/// of the finer level over its footprint.
fn downsample(l: &MipLevel) -> MipLevel {
    let (w, h) = ((l.width / 2).max(1), (l.height / 2).max(1));
    let xs: Vec<_> = (0..w).map(|x| footprint(x, l.width, w)).collect();
    let ys: Vec<_> = (0..h).map(|y| footprint(y, l.height, h)).collect();
    let mut texels = Vec::with_capacity(w * h);
    for wy in &ys {
        for wx in &xs {
            let mut acc = [0.0f64; 4];
            for &(sy, fy) in wy {
                for &(sx, fx) in wx {
                    let t = l.texels[sy * l.width + sx];
                    for k in 0..4 {
                        acc[k] += f64::from(t[k]) * fx * fy;
                    }
                }
            }
            texels.push(acc.map(|v| v as f32));
        }
    }
    MipLevel {
        width: w,
        height: h,
        texels,
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use ocellus_engine::value::{Channels, Image};

    use super::*;

    fn texture(
        w: usize,
        h: usize,
        gray: Vec<f32>,
        wrap: TextureWrap,
        filter: TextureFilter,
    ) -> Texture {
        Texture {
            image: Arc::new(Image::new(w, h, Channels::Gray, PixelData::F32(gray)).unwrap()),
            wrap,
            filter,
            border: [0.25, 0.5, 0.75, 1.0],
            max_anisotropy: 16,
            uv_scale: [1.0, 1.0],
        }
    }

    /// 2×2: top row 0, 1; bottom row 2, 3.
    fn quad(wrap: TextureWrap, filter: TextureFilter) -> TextureSampler {
        TextureSampler::new(&texture(2, 2, vec![0.0, 1.0, 2.0, 3.0], wrap, filter)).unwrap()
    }

    #[test]
    fn nearest_uses_v_up_texel_centres() {
        let s = quad(TextureWrap::Repeat, TextureFilter::Nearest);
        // Bottom-left quadrant is the bottom row's first texel.
        assert_eq!(s.sample([0.25, 0.25])[0], 2.0);
        assert_eq!(s.sample([0.75, 0.25])[0], 3.0);
        assert_eq!(s.sample([0.25, 0.75])[0], 0.0);
        assert_eq!(s.sample([0.75, 0.75])[0], 1.0);
        assert_eq!(s.sample([0.75, 0.75])[3], 1.0);
    }

    #[test]
    fn bilinear_interpolates_between_texel_centres() {
        let s = quad(TextureWrap::ClampToEdge, TextureFilter::Bilinear);
        // The image centre is the mean of all four.
        assert!((s.sample([0.5, 0.5])[0] - 1.5).abs() < 1e-6);
        // Halfway between the top texels' centres.
        assert!((s.sample([0.5, 0.75])[0] - 0.5).abs() < 1e-6);
        // A texel centre returns the texel.
        assert!((s.sample([0.25, 0.25])[0] - 2.0).abs() < 1e-6);
        // Clamp to edge: beyond the corner, the corner texel.
        assert!((s.sample([-3.0, 9.0])[0] - 0.0).abs() < 1e-6);
    }

    #[test]
    fn address_modes() {
        let n = TextureFilter::Nearest;
        let r = quad(TextureWrap::Repeat, n);
        let m = quad(TextureWrap::MirroredRepeat, n);
        let c = quad(TextureWrap::ClampToEdge, n);
        let b = quad(TextureWrap::ClampToBorder, n);
        // u = 1.25 → repeat reads u = 0.25; mirrored reads u = 0.75.
        assert_eq!(r.sample([1.25, 0.25])[0], 2.0);
        assert_eq!(m.sample([1.25, 0.25])[0], 3.0);
        assert_eq!(m.sample([-0.25, 0.25])[0], 2.0);
        assert_eq!(r.sample([-0.25, 0.25])[0], 3.0);
        assert_eq!(c.sample([7.0, 0.25])[0], 3.0);
        assert_eq!(b.sample([1.25, 0.25]), [0.25, 0.5, 0.75, 1.0]);
        assert_eq!(b.sample([0.25, 0.25])[0], 2.0);
        // Bilinear with a border blends towards the border colour at the edge.
        let bb = quad(TextureWrap::ClampToBorder, TextureFilter::Bilinear);
        let edge = bb.sample([1.0, 0.25]);
        assert!((edge[0] - 0.5 * (3.0 + 0.25)).abs() < 1e-6, "{edge:?}");
    }

    #[test]
    fn mip_chain_preserves_the_mean_for_odd_sizes() {
        let (w, h) = (5, 3);
        let data: Vec<f32> = (0..w * h).map(|i| ((i * 7) % 11) as f32).collect();
        let mean = data.iter().sum::<f32>() / data.len() as f32;
        let s = TextureSampler::new(&texture(
            w,
            h,
            data,
            TextureWrap::Repeat,
            TextureFilter::Trilinear,
        ))
        .unwrap();
        let sizes: Vec<_> = s.levels.iter().map(|l| (l.width, l.height)).collect();
        assert_eq!(sizes, vec![(5, 3), (2, 1), (1, 1)]);
        for l in &s.levels {
            let m = l.texels.iter().map(|t| t[0]).sum::<f32>() / l.texels.len() as f32;
            assert!((m - mean).abs() < 1e-5, "{m} vs {mean}");
        }
    }

    fn checker(n: usize, cell: usize, filter: TextureFilter) -> TextureSampler {
        let data = (0..n * n)
            .map(|i| (((i % n) / cell + (i / n) / cell) % 2) as f32)
            .collect();
        TextureSampler::new(&texture(n, n, data, TextureWrap::Repeat, filter)).unwrap()
    }

    #[test]
    fn minified_checkerboard_averages_to_grey_and_level_zero_stays_sharp() {
        let s = checker(64, 1, TextureFilter::Trilinear);
        // One pixel spans 16 texels: λ = 4, the 4×4 level, where every texel is 0.5.
        let d = 16.0 / 64.0;
        for uv in [[0.1, 0.2], [0.37, 0.81], [0.9, 0.05]] {
            let v = s.sample_grad(uv, [d, 0.0], [0.0, d])[0];
            assert!((v - 0.5).abs() < 1e-6, "{v}");
        }
        // One texel per pixel: level 0, texel centres are pure black or white.
        let d = 1.0 / 64.0;
        let v = s.sample_grad([0.5 / 64.0, 1.0 - 0.5 / 64.0], [d, 0.0], [0.0, d])[0];
        assert_eq!(v, 0.0);
        let v = s.sample_grad([1.5 / 64.0, 1.0 - 0.5 / 64.0], [d, 0.0], [0.0, d])[0];
        assert_eq!(v, 1.0);
        // Halfway between levels blends them.
        let a = s.sample_lod([1.5 / 64.0, 1.0 - 0.5 / 64.0], 0.0)[0];
        let b = s.sample_lod([1.5 / 64.0, 1.0 - 0.5 / 64.0], 1.0)[0];
        let m = s.sample_lod([1.5 / 64.0, 1.0 - 0.5 / 64.0], 0.5)[0];
        assert!((m - 0.5 * (a + b)).abs() < 1e-6);
    }

    #[test]
    fn anisotropic_filtering_keeps_detail_across_a_stretched_footprint() {
        // Horizontal stripes one texel high: varies along v only.
        let n = 64;
        let data = (0..n * n).map(|i| ((i / n) % 2) as f32).collect();
        let tri = TextureSampler::new(&texture(
            n,
            n,
            data,
            TextureWrap::Repeat,
            TextureFilter::Trilinear,
        ))
        .unwrap();
        let mut aniso = tri.clone();
        aniso.filter = TextureFilter::Anisotropic;
        // Footprint: 8 texels along u, 1 along v.
        let (dx, dy) = ([8.0 / n as f32, 0.0], [0.0, 1.0 / n as f32]);
        let uv = [0.5, 1.0 - 0.5 / n as f32]; // row 0's centre: value 0
        let t = tri.sample_grad(uv, dx, dy)[0];
        let a = aniso.sample_grad(uv, dx, dy)[0];
        assert!((t - 0.5).abs() < 1e-6, "trilinear blurs to grey: {t}");
        assert!(a.abs() < 1e-6, "anisotropic keeps the stripe: {a}");
        let uv = [0.5, 1.0 - 1.5 / n as f32]; // row 1: value 1
        assert!((aniso.sample_grad(uv, dx, dy)[0] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn equirectangular_directions() {
        // 4×2 map: top row (+y hemisphere) 1..4, bottom row 5..8.
        let data = (1..=8).map(|v| v as f32).collect();
        let s = TextureSampler::new(&texture(
            4,
            2,
            data,
            TextureWrap::Repeat,
            TextureFilter::Nearest,
        ))
        .unwrap();
        // Up is the top row; looking along −z is the centre column (u = 0.5 → texel 2).
        assert!(s.sample_direction([0.0, 1.0, -1e-3])[0] <= 4.0);
        assert_eq!(s.sample_direction([0.0, 0.3, -1.0])[0], 3.0);
        assert_eq!(s.sample_direction([0.0, -0.3, -1.0])[0], 7.0);
        // +x is a quarter turn from −z: u = 0.75 → texel 3.
        assert_eq!(s.sample_direction([1.0, 0.3, 0.0])[0], 4.0);
    }

    #[test]
    fn bad_textures_are_refused() {
        let mut t = texture(
            1,
            1,
            vec![f32::NAN],
            TextureWrap::Repeat,
            TextureFilter::Nearest,
        );
        assert!(TextureSampler::new(&t).unwrap_err().contains("non-finite"));
        t.image = Arc::new(Image::new(1, 1, Channels::Gray, PixelData::F32(vec![0.5])).unwrap());
        t.max_anisotropy = 0;
        assert!(TextureSampler::new(&t).is_err());
        t.max_anisotropy = 4;
        let s = TextureSampler::new(&t).unwrap();
        // A 1×1 texture has one level and reads the same everywhere.
        assert_eq!(s.levels.len(), 1);
        assert_eq!(s.sample_grad([9.0, -3.0], [1e9, 0.0], [0.0, 1e-9])[0], 0.5);
        assert_eq!(
            s.sample_grad([f32::NAN, 0.0], [f32::NAN, 0.0], [0.0, 0.0])[0],
            0.5
        );
    }

    #[test]
    fn u8_and_rgb_texels_convert() {
        let t = Texture {
            image: Arc::new(
                Image::new(1, 1, Channels::Rgb, PixelData::U8(vec![255, 51, 0])).unwrap(),
            ),
            wrap: TextureWrap::Repeat,
            filter: TextureFilter::Bilinear,
            border: [0.0; 4],
            max_anisotropy: 1,
            uv_scale: [3.0, 3.0],
        };
        let s = TextureSampler::new(&t).unwrap();
        assert_eq!(s.sample([0.3, 0.3]), [1.0, 0.2, 0.0, 1.0]);
    }
}
