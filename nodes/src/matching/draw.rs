//! `match.draw`: two images side by side with lines joining matched keypoints (OpenCV's
//! `drawMatches`).

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Keypoint, Match, PixelData, Value};
use ocellus_engine::{param_enum, params};

use super::{keypoints, matches};
use crate::capture::pattern::splitmix64;

/// Largest circle radius, px.
pub const MAX_RADIUS: u32 = 256;

param_enum! {
    /// How match lines are coloured.
    pub enum LineColor {
        /// A bright colour per match, from a fixed-seed hash of the match's index.
        Random = "random",
        /// Green (smallest distance drawn) to red (largest).
        Distance = "distance",
    }
}

params! {
    /// Parameters of `match.draw`.
    pub struct DrawParams {
        /// Line colours: "random" or "distance". Default "random".
        color: LineColor = LineColor::Random,
        /// Draw at most this many matches, those of smallest distance (ties: input order);
        /// 0 draws all. Default 0.
        max_matches: u32 = 0,
        /// Radius of the circles drawn around both keypoints of each drawn match, px; 0 draws
        /// none. Default 3.
        radius_px: u32 = 3 => [max = 256, unit = "px"],
        /// Seed of the "random" colours. Default 0.
        seed: u64 = 0,
    }
}

/// Match drawing (`match.draw`). See [`draw_matches`].
#[derive(Debug, Clone, PartialEq)]
pub struct DrawMatches {
    params: DrawParams,
}

impl Op for DrawMatches {
    type Params = DrawParams;
    const ID: &'static str = "match.draw";
    const SUMMARY: &'static str = "Draws two images side by side with lines joining their matches.";
    const DOC: &'static str = r#"
Places the left and right images side by side (right one shifted by the left's width, the
canvas as tall as the taller, black elsewhere) as RGB u8, and for each drawn match joins
`keypoints_left[query]` to `keypoints_right[train]` with a 1-px line (Bresenham, endpoints
rounded) and, with `radius_px > 0`, circles (midpoint algorithm) around both ends.

Colours: "random" gives every match a bright colour from a hash of its index and `seed`
(stable between runs); "distance" runs from green (smallest drawn distance) to red (largest).
`max_matches > 0` draws only that many matches of smallest distance. Images are converted to
RGB u8: gray replicated, alpha dropped, u16 as round(v / 257), f32 as round(clamp(v, 0, 1) ·
255). Matches with a keypoint farther than 4 × (width + height) from the canvas (or non-finite) are
skipped; match indices outside the keypoint lists
are an error.

Reference: OpenCV `cv::drawMatches` (which draws anti-aliased lines; ours are plain 1-px).

Example:
    "vis": (op: "match.draw", inputs: { "left": "img1.image", "right": "img2.image",
            "keypoints_left": "orb1.keypoints", "keypoints_right": "orb2.keypoints",
            "matches": "match.matches" }, params: (max_matches: 200)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("left", PortType::Image, "First image (any format)."),
            PortSpec::new("right", PortType::Image, "Second image (any format)."),
            PortSpec::new(
                "keypoints_left",
                PortType::Keypoints,
                "Keypoints of the left image (indexed by match.query).",
            ),
            PortSpec::new(
                "keypoints_right",
                PortType::Keypoints,
                "Keypoints of the right image (indexed by match.train).",
            ),
            PortSpec::new("matches", PortType::Matches, "Matches to draw."),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "RGB u8 canvas, (left width + right width) × max height.",
        )]
    }

    fn new(params: DrawParams) -> Result<Self, String> {
        if params.radius_px > MAX_RADIUS {
            return Err(format!(
                "`radius_px` must be ≤ {MAX_RADIUS}, got {}",
                params.radius_px
            ));
        }
        Ok(DrawMatches { params })
    }
}

impl Operator for DrawMatches {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let left = inputs.image("left")?;
        let right = inputs.image("right")?;
        let kl = keypoints(inputs, "keypoints_left")?;
        let kr = keypoints(inputs, "keypoints_right")?;
        let m = matches(inputs, "matches")?;
        let image = draw_matches(left, right, kl, kr, m, &self.params)?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

/// RGB u8 samples of `image`.
fn rgb_u8(image: &Image) -> Vec<u8> {
    let c = image.channels().count();
    let to8: Vec<u8> = match image.data() {
        PixelData::U8(v) => v.clone(),
        PixelData::U16(v) => v
            .iter()
            .map(|&s| ((u32::from(s) + 128) / 257) as u8)
            .collect(),
        PixelData::F32(v) => v
            .iter()
            .map(|&s| {
                let s = if s.is_nan() { 0.0 } else { s.clamp(0.0, 1.0) };
                (s * 255.0).round() as u8
            })
            .collect(),
    };
    match c {
        1 => to8.iter().flat_map(|&g| [g, g, g]).collect(),
        3 => to8,
        _ => to8
            .chunks_exact(c)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect(),
    }
}

/// An RGB u8 canvas.
struct Canvas {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl Canvas {
    #[inline]
    fn put(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            let i = (y as usize * self.width + x as usize) * 3;
            self.data[i..i + 3].copy_from_slice(&c);
        }
    }

    /// Bresenham line between two pixels.
    fn line(&mut self, (mut x0, mut y0): (i64, i64), (x1, y1): (i64, i64), c: [u8; 3]) {
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let mut err = dx + dy;
        loop {
            self.put(x0, y0, c);
            if x0 == x1 && y0 == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x0 += sx;
            }
            if e2 <= dx {
                err += dx;
                y0 += sy;
            }
        }
    }

    /// Midpoint circle outline.
    fn circle(&mut self, (cx, cy): (i64, i64), r: i64, c: [u8; 3]) {
        let (mut x, mut y, mut err) = (r, 0i64, 1 - r);
        while x >= y {
            for (px, py) in [
                (x, y),
                (y, x),
                (-y, x),
                (-x, y),
                (-x, -y),
                (-y, -x),
                (y, -x),
                (x, -y),
            ] {
                self.put(cx + px, cy + py, c);
            }
            y += 1;
            if err < 0 {
                err += 2 * y + 1;
            } else {
                x -= 1;
                err += 2 * (y - x) + 1;
            }
        }
    }
}

/// Side-by-side drawing of `matches` between `left` and `right` (see the operator doc).
pub fn draw_matches(
    left: &Image,
    right: &Image,
    keypoints_left: &[Keypoint],
    keypoints_right: &[Keypoint],
    matches: &[Match],
    params: &DrawParams,
) -> Result<Image, OpError> {
    for m in matches {
        if m.query as usize >= keypoints_left.len() || m.train as usize >= keypoints_right.len() {
            return Err(OpError::input(
                "matches",
                format!(
                    "match ({}, {}) indexes past the keypoints ({} left, {} right)",
                    m.query,
                    m.train,
                    keypoints_left.len(),
                    keypoints_right.len()
                ),
            ));
        }
    }
    let (wl, wr) = (left.width(), right.width());
    let width = wl + wr;
    let height = left.height().max(right.height());
    let mut canvas = Canvas {
        width,
        height,
        data: vec![0; width * height * 3],
    };
    for (image, x0) in [(left, 0), (right, wl)] {
        let rgb = rgb_u8(image);
        let w = image.width();
        if w == 0 {
            continue;
        }
        for (y, row) in rgb.chunks_exact(w * 3).enumerate() {
            let start = (y * width + x0) * 3;
            canvas.data[start..start + w * 3].copy_from_slice(row);
        }
    }
    // The matches to draw: all, or the `max_matches` of smallest distance (stable).
    let mut order: Vec<usize> = (0..matches.len()).collect();
    if params.max_matches > 0 && (params.max_matches as usize) < matches.len() {
        order.sort_by(|&a, &b| matches[a].distance.total_cmp(&matches[b].distance));
        order.truncate(params.max_matches as usize);
        order.sort_unstable();
    }
    let (lo, hi) = order
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &i| {
            (l.min(matches[i].distance), h.max(matches[i].distance))
        });
    // Endpoints farther than this from the canvas are skipped (bounds the line length).
    let reach = 4.0 * (width + height) as f32 + 16.0;
    let pixel = |k: &Keypoint, dx: usize| -> Option<(i64, i64)> {
        (k.x.abs() <= reach && k.y.abs() <= reach)
            .then(|| (k.x.round() as i64 + dx as i64, k.y.round() as i64))
    };
    for &i in &order {
        let m = matches[i];
        let colour = match params.color {
            LineColor::Random => {
                let h = splitmix64(params.seed ^ splitmix64(i as u64));
                [
                    64 + (h % 192) as u8,
                    64 + ((h >> 8) % 192) as u8,
                    64 + ((h >> 16) % 192) as u8,
                ]
            }
            LineColor::Distance => {
                let t = if hi > lo && m.distance.is_finite() {
                    ((m.distance - lo) / (hi - lo)).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                [
                    (255.0 * t).round() as u8,
                    (255.0 * (1.0 - t)).round() as u8,
                    0,
                ]
            }
        };
        let (Some(a), Some(b)) = (
            pixel(&keypoints_left[m.query as usize], 0),
            pixel(&keypoints_right[m.train as usize], wl),
        ) else {
            continue;
        };
        canvas.line(a, b, colour);
        if params.radius_px > 0 {
            canvas.circle(a, i64::from(params.radius_px), colour);
            canvas.circle(b, i64::from(params.radius_px), colour);
        }
    }
    Image::from_u8(width, height, Channels::Rgb, canvas.data)
        .map_err(|e| OpError::failed(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 1.0,
            angle: -1.0,
            response: 0.0,
            octave: 0,
        }
    }

    fn px(img: &Image, x: usize, y: usize) -> [u8; 3] {
        let d = img.as_u8().unwrap();
        let i = (y * img.width() + x) * 3;
        [d[i], d[i + 1], d[i + 2]]
    }

    #[test]
    fn size_copies_and_lines() {
        let left = Image::from_u8(10, 6, Channels::Gray, vec![40; 60]).unwrap();
        let right = Image::from_f32(8, 9, Channels::Rgba, vec![1.0; 8 * 9 * 4]).unwrap();
        let kl = [kp(2.0, 2.0), kp(5.0, 5.0)];
        let kr = [kp(2.0, 2.0), kp(1.0, 8.0)];
        let m = [
            Match {
                query: 0,
                train: 0,
                distance: 1.0,
            },
            Match {
                query: 1,
                train: 1,
                distance: 3.0,
            },
        ];
        let params = DrawParams {
            color: LineColor::Distance,
            radius_px: 0,
            ..DrawParams::default()
        };
        let img = draw_matches(&left, &right, &kl, &kr, &m, &params).unwrap();
        assert_eq!(
            (img.width(), img.height(), img.channels()),
            (18, 9, Channels::Rgb)
        );
        // Background copies: left gray 40, right white, black below the left image.
        assert_eq!(px(&img, 0, 0), [40, 40, 40]);
        assert_eq!(px(&img, 17, 0), [255, 255, 255]);
        assert_eq!(px(&img, 3, 7), [0, 0, 0]);
        // Match 0 (smallest distance, green) is the horizontal line y = 2 from x 2 to 12.
        for x in 2..=12 {
            assert_eq!(px(&img, x, 2), [0, 255, 0], "x {x}");
        }
        assert_eq!(px(&img, 1, 2), [40, 40, 40]);
        // Match 1 (red) ends at (5, 5) and (11, 8).
        assert_eq!(px(&img, 5, 5), [255, 0, 0]);
        assert_eq!(px(&img, 11, 8), [255, 0, 0]);
        // Only the best match.
        let params = DrawParams {
            max_matches: 1,
            radius_px: 2,
            ..DrawParams::default()
        };
        let img = draw_matches(&left, &right, &kl, &kr, &m, &params).unwrap();
        assert_eq!(px(&img, 11, 8), [255, 255, 255]);
        assert_ne!(px(&img, 7, 2), [40, 40, 40]);
        // Circle of radius 2 around (2, 2): (4, 2) and (2, 0) are on it, the centre's
        // neighbour (3, 3) is not.
        let c = px(&img, 7, 2);
        assert_eq!(px(&img, 2, 0), c);
        assert_eq!(px(&img, 0, 2), c);
        assert_eq!(px(&img, 3, 3), [40, 40, 40]);
    }

    #[test]
    fn errors_and_empty() {
        let e = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        let img = draw_matches(&e, &e, &[], &[], &[], &DrawParams::default()).unwrap();
        assert_eq!((img.width(), img.height()), (0, 0));
        let bad = [Match {
            query: 0,
            train: 3,
            distance: 0.0,
        }];
        assert!(draw_matches(&e, &e, &[kp(0.0, 0.0)], &[], &bad, &DrawParams::default()).is_err());
        // Keypoints outside the canvas are clipped, not errors.
        let one = Image::from_u16(3, 3, Channels::Rgb, vec![65535; 27]).unwrap();
        let far = [kp(-50.0, 1e6)];
        let m = [Match {
            query: 0,
            train: 0,
            distance: 0.0,
        }];
        let img = draw_matches(&one, &one, &far, &far, &m, &DrawParams::default()).unwrap();
        assert_eq!(img.width(), 6);
    }
}
