//! `segment.region_grow`: region growing from seed points by breadth-first search.
//!
//! [`region_grow`] grows one region per seed over 4- or 8-connected pixels whose value is within
//! a tolerance of the seed's value or of the region's running mean. All seeds grow in one
//! breadth-first search, so where regions compete the pixel goes to whichever reaches it first
//! (ties by seed order): the result is deterministic.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};

use super::{MAX_LABEL, label_image};

param_enum! {
    /// What a candidate pixel is compared with in `segment.region_grow`.
    pub enum GrowCriterion {
        /// The seed pixel's value: `|I − I_seed| ≤ tolerance`.
        Seed = "seed",
        /// The region's running mean when the pixel is examined: `|I − mean| ≤ tolerance`.
        Mean = "mean",
    }
}

params! {
    /// Parameters of `segment.region_grow`.
    pub struct RegionGrowParams {
        /// Seed points `[x, y]` in pixels (pixel centres at integer coordinates; rounded to the
        /// nearest pixel). Region i + 1 grows from seed i; seeds on the `seeds` input port are
        /// appended after these. Default: none.
        seeds: Vec<[f64; 2]> = Vec::new(),
        /// `seed` (compare with the seed pixel) or `mean` (with the region's running mean).
        /// Default `seed`.
        criterion: GrowCriterion = GrowCriterion::Seed,
        /// Largest accepted distance, in sample units (0–255 for u8, 0–65535 for u16, the
        /// samples themselves for f32); Euclidean over channels for colour images. ≥ 0.
        /// Default 10.
        tolerance: f64 = 10.0,
        /// Pixel neighbourhood: 4 or 8. Default 4.
        connectivity: u32 = 4,
    }
}

/// Region growing (`segment.region_grow`). See [`region_grow`].
#[derive(Debug, Clone, PartialEq)]
pub struct RegionGrow {
    seeds: Vec<[f64; 2]>,
    criterion: GrowCriterion,
    tolerance: f64,
    eight: bool,
}

impl Op for RegionGrow {
    type Params = RegionGrowParams;
    const ID: &'static str = "segment.region_grow";
    const SUMMARY: &'static str =
        "Grows a region from each seed point over connected pixels of similar value.";
    const DOC: &'static str = r#"
Grows one region per seed point. A pixel joins a region when it is a 4- (or 8-) neighbour of a
pixel of the region and its value is within `tolerance` of the reference: the seed pixel's value
(`criterion: seed`) or the region's mean at the moment the pixel is examined (`criterion:
mean`, updated as pixels join). Colour images (RGB, RGBA: every channel) use the Euclidean
distance over channels; any depth (u8, u16, f32), tolerance in sample units.

Method: one breadth-first search (FIFO queue) started from all seeds in order, visiting
neighbours in raster order (up-left, up, up-right, left, right, down-left, down, down-right; the
four edge neighbours for connectivity 4). A pixel belongs to the first region that reaches and
accepts it; a pixel rejected by one region can still join another. A seed falling on a pixel
already taken (a repeated seed) gets an empty region. The result is deterministic.

Outputs: `labels` (gray f32: i + 1 for the region of seed i, 0 where nothing grew) and `mask`
(gray u8: 255 inside any region, 0 elsewhere). Seeds outside the image are an error; no seeds at
all give empty outputs (all 0). The closest OpenCV function is `cv::floodFill` with
`FLOODFILL_FIXED_RANGE` (criterion `seed`, one seed, per-channel box instead of Euclidean ball).

Reference: R. Adams and L. Bischof, "Seeded region growing", IEEE PAMI 16(6), 1994 (this is
the simpler tolerance variant).

Example:
    "region": (op: "segment.region_grow", inputs: { "image": "photo.image" }, params: (seeds: [(120.0, 80.0)], tolerance: 12.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "image",
                PortType::Image,
                "Image to segment, any pixel format.",
            ),
            PortSpec::new(
                "seeds",
                PortType::Points2D,
                "More seed points (x, y) in pixels, after the `seeds` parameter's.",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "labels",
                PortType::Image,
                "Gray f32: i + 1 for seed i's region, 0 elsewhere.",
            ),
            PortSpec::new(
                "mask",
                PortType::Image,
                "Gray u8: 255 in any region, 0 elsewhere.",
            ),
        ]
    }

    fn new(params: RegionGrowParams) -> Result<Self, String> {
        let RegionGrowParams {
            seeds,
            criterion,
            tolerance,
            connectivity,
        } = params;
        if !tolerance.is_finite() || tolerance < 0.0 {
            return Err(format!(
                "`tolerance` must be finite and ≥ 0, got {tolerance}"
            ));
        }
        if let Some(s) = seeds
            .iter()
            .find(|s| !s[0].is_finite() || !s[1].is_finite())
        {
            return Err(format!("`seeds` must be finite, got {s:?}"));
        }
        let eight = match connectivity {
            4 => false,
            8 => true,
            c => return Err(format!("`connectivity` must be 4 or 8, got {c}")),
        };
        Ok(RegionGrow {
            seeds,
            criterion,
            tolerance,
            eight,
        })
    }
}

impl Operator for RegionGrow {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let mut seeds = self.seeds.clone();
        match inputs.get("seeds") {
            None => {}
            Some(Value::Points2D(points)) => seeds.extend(points.iter().copied()),
            Some(other) => {
                return Err(OpError::input(
                    "seeds",
                    format!("expected Points2D, got {}", other.port_type()),
                ));
            }
        }
        let labels = region_grow(image, &seeds, self.criterion, self.tolerance, self.eight)
            .map_err(|e| OpError::input("seeds", e))?;
        let (w, h) = (image.width(), image.height());
        let mask: Vec<u8> = labels
            .iter()
            .map(|&l| if l > 0 { 255 } else { 0 })
            .collect();
        let mask = Image::from_u8(w, h, Channels::Gray, mask)
            .map_err(|e| OpError::failed(e.to_string()))?;
        let labels = label_image(w, h, labels.into_iter().map(|l| l as f32).collect())
            .map_err(OpError::failed)?;
        Ok(Outputs::new()
            .with("labels", Value::image(labels))
            .with("mask", Value::image(mask)))
    }
}

/// The samples of `image` widened to f64, interleaved.
fn samples_f64(image: &Image) -> Vec<f64> {
    match image.data() {
        PixelData::U8(s) => s.iter().map(|&v| v as f64).collect(),
        PixelData::U16(s) => s.iter().map(|&v| v as f64).collect(),
        PixelData::F32(s) => s.iter().map(|&v| v as f64).collect(),
    }
}

/// Grows a region from every seed (`[x, y]` px, rounded to the nearest pixel) of `image`; see
/// the operator's DOC. Returns `width × height` labels: i + 1 for seed i's region, 0 elsewhere.
/// Errors when a seed lies outside the image or there are more than 2^24 seeds.
pub fn region_grow(
    image: &Image,
    seeds: &[[f64; 2]],
    criterion: GrowCriterion,
    tolerance: f64,
    eight: bool,
) -> Result<Vec<u32>, String> {
    let (w, h) = (image.width(), image.height());
    let c = image.channels().count();
    if seeds.len() > MAX_LABEL {
        return Err(format!("{} seeds: more than 2^24 labels", seeds.len()));
    }
    let mut pixels = Vec::with_capacity(seeds.len());
    for s in seeds {
        let (x, y) = (s[0].round(), s[1].round());
        if !(x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64) {
            return Err(format!(
                "seed ({}, {}) lies outside the {w}×{h} image",
                s[0], s[1]
            ));
        }
        pixels.push(y as usize * w + x as usize);
    }
    let data = samples_f64(image);
    let value = |p: usize| &data[p * c..p * c + c];
    let tol2 = tolerance * tolerance;
    let mut labels = vec![0u32; w * h];
    // Per region: the reference sum (the seed value, or the running sum) and pixel count.
    let mut sums = vec![0f64; seeds.len() * c];
    let mut counts = vec![0u64; seeds.len()];
    let mut queue: Vec<u32> = Vec::new();
    for (i, &p) in pixels.iter().enumerate() {
        if labels[p] == 0 {
            labels[p] = i as u32 + 1;
            sums[i * c..i * c + c].copy_from_slice(value(p));
            counts[i] = 1;
            queue.push(p as u32);
        }
    }
    let mean = criterion == GrowCriterion::Mean;
    let offsets: &[(i64, i64)] = if eight {
        &[
            (-1, -1),
            (0, -1),
            (1, -1),
            (-1, 0),
            (1, 0),
            (-1, 1),
            (0, 1),
            (1, 1),
        ]
    } else {
        &[(0, -1), (-1, 0), (1, 0), (0, 1)]
    };
    let mut head = 0;
    while head < queue.len() {
        let p = queue[head] as usize;
        head += 1;
        let region = labels[p] as usize - 1;
        let (px, py) = ((p % w) as i64, (p / w) as i64);
        for &(dx, dy) in offsets {
            let (nx, ny) = (px + dx, py + dy);
            if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                continue;
            }
            let q = ny as usize * w + nx as usize;
            if labels[q] != 0 {
                continue;
            }
            let scale = if mean {
                1.0 / counts[region] as f64
            } else {
                1.0
            };
            let reference = &sums[region * c..region * c + c];
            let d2: f64 = value(q)
                .iter()
                .zip(reference)
                .map(|(&v, &r)| (v - r * scale).powi(2))
                .sum();
            if d2 <= tol2 {
                labels[q] = region as u32 + 1;
                if mean {
                    for (s, &v) in sums[region * c..region * c + c].iter_mut().zip(value(q)) {
                        *s += v;
                    }
                    counts[region] += 1;
                }
                queue.push(q as u32);
            }
        }
    }
    Ok(labels)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::test_support::randoms;
    use proptest::prelude::*;

    fn gray(w: usize, h: usize, v: Vec<u8>) -> Image {
        Image::from_u8(w, h, Channels::Gray, v).unwrap()
    }

    #[test]
    fn hand_made_two_regions_and_connectivity() {
        #[rustfmt::skip]
        let img = gray(5, 4, vec![
            10, 12, 90, 91, 90,
            11, 13, 90, 50, 90,
            90, 90, 14, 90, 90,
            90, 90, 90, 90, 90,
        ]);
        let seeds = [[0.0, 0.0], [4.0, 3.0]];
        let l = region_grow(&img, &seeds, GrowCriterion::Seed, 2.0, false).unwrap();
        #[rustfmt::skip]
        assert_eq!(l, vec![
            1, 1, 2, 2, 2,
            1, 0, 2, 0, 2,
            2, 2, 0, 2, 2,
            2, 2, 2, 2, 2,
        ]);
        // With 8-connectivity and tolerance 4, region 1 also takes 13 and then, diagonally, 14.
        let l = region_grow(&img, &seeds, GrowCriterion::Seed, 4.0, true).unwrap();
        assert_eq!(&l[..5], &[1, 1, 2, 2, 2]);
        assert_eq!(l[6], 1); // 13 joins region 1 (|13 − 10| ≤ 4)
        assert_eq!(l[12], 1); // 14 diagonal to 13
        assert_eq!(l[8], 0); // 50 joins nothing
    }

    #[test]
    fn mean_criterion_follows_the_region_seed_criterion_stops() {
        // 0, 5, 7 with tolerance 5: 7 is 7 from the seed but 4.5 from the mean of {0, 5}.
        let img = gray(3, 1, vec![0, 5, 7]);
        let s = region_grow(&img, &[[0.0, 0.0]], GrowCriterion::Seed, 5.0, false).unwrap();
        assert_eq!(s, vec![1, 1, 0]);
        let m = region_grow(&img, &[[0.0, 0.0]], GrowCriterion::Mean, 5.0, false).unwrap();
        assert_eq!(m, vec![1, 1, 1]);
        let m = region_grow(&img, &[[0.0, 0.0]], GrowCriterion::Mean, 4.9, false).unwrap();
        assert_eq!(m, vec![1, 0, 0]);
    }

    #[test]
    fn colour_uses_euclidean_distance() {
        // (3, 4, 0) from (0, 0, 0) is at distance 5: in with tolerance 5, out with 4.9.
        let img = Image::from_u8(2, 1, Channels::Rgb, vec![0, 0, 0, 3, 4, 0]).unwrap();
        let a = region_grow(&img, &[[0.0, 0.0]], GrowCriterion::Seed, 5.0, false).unwrap();
        assert_eq!(a, vec![1, 1]);
        let b = region_grow(&img, &[[0.0, 0.0]], GrowCriterion::Seed, 4.9, false).unwrap();
        assert_eq!(b, vec![1, 0]);
    }

    #[test]
    fn repeated_seeds_tiny_and_errors() {
        let img = gray(3, 3, vec![7; 9]);
        let l = region_grow(
            &img,
            &[[1.2, 0.8], [1.0, 1.0]],
            GrowCriterion::Seed,
            0.0,
            false,
        )
        .unwrap();
        assert!(l.iter().all(|&v| v == 1));
        assert!(region_grow(&img, &[[3.0, 0.0]], GrowCriterion::Seed, 0.0, false).is_err());
        assert!(region_grow(&img, &[[-0.6, 0.0]], GrowCriterion::Seed, 0.0, false).is_err());
        assert_eq!(
            region_grow(&img, &[], GrowCriterion::Mean, 1.0, true).unwrap(),
            vec![0; 9]
        );
        let one = Image::from_f32(1, 1, Channels::Gray, vec![f32::MAX]).unwrap();
        let l = region_grow(&one, &[[0.0, 0.0]], GrowCriterion::Mean, 0.0, true).unwrap();
        assert_eq!(l, vec![1]);
        let empty = Image::from_u16(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(
            region_grow(&empty, &[], GrowCriterion::Seed, 0.0, true)
                .unwrap()
                .is_empty()
        );
        let bad = RegionGrowParams {
            tolerance: f64::NAN,
            ..RegionGrowParams::default()
        };
        assert!(RegionGrow::new(bad).is_err());
    }

    #[test]
    fn operator_merges_param_and_port_seeds() {
        let op = RegionGrow::new(RegionGrowParams {
            seeds: vec![[0.0, 0.0]],
            tolerance: 0.0,
            ..RegionGrowParams::default()
        })
        .unwrap();
        let img = gray(3, 1, vec![1, 9, 9]);
        let specs = RegionGrow::inputs();
        let values = [
            Some(Value::image(img)),
            Some(Value::Points2D(std::sync::Arc::new(vec![[2.0, 0.0]]))),
        ];
        let ctx = RunContext {
            node: "g".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Image(l)) = out.take("labels") else {
            panic!("labels")
        };
        assert_eq!(l.as_f32().unwrap(), &[1.0, 2.0, 2.0]);
        let Some(Value::Image(m)) = out.take("mask") else {
            panic!("mask")
        };
        assert_eq!(m.as_u8().unwrap(), &[255, 255, 255]);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]

        /// With one seed and the seed criterion, the region is exactly the connected component
        /// (of the "within tolerance" mask) containing the seed.
        #[test]
        fn one_seed_equals_component_of_tolerance_mask(
            w in 1usize..40, h in 1usize..40, seed in 0u64..10_000, tol in 0.0f64..120.0,
            eight in any::<bool>(),
        ) {
            let v: Vec<u8> = randoms(seed, w * h).iter().map(|r| (r * 256.0) as u8).collect();
            let img = gray(w, h, v.clone());
            let (sx, sy) = (w / 2, h / 2);
            let s = v[sy * w + sx] as f64;
            let l = region_grow(&img, &[[sx as f64, sy as f64]], GrowCriterion::Seed, tol, eight)
                .unwrap();
            let within: Vec<f32> =
                v.iter().map(|&x| if (x as f64 - s).abs() <= tol { 1.0 } else { 0.0 }).collect();
            let cc = super::super::components::connected_components(
                &Image::from_f32(w, h, Channels::Gray, within).unwrap(), eight, false).unwrap();
            let target = cc.labels[sy * w + sx];
            for (&got, &component) in l.iter().zip(&cc.labels) {
                prop_assert_eq!(got == 1, component == target);
            }
        }
    }
}
