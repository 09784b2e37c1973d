//! Binary morphology: `filter.hit_or_miss`, `filter.thinning`, `filter.thickening` and
//! `filter.skeleton`.
//!
//! Inputs are single-channel u8 images read as binary (nonzero = foreground); outputs are 0/255.
//!
//! - Hit-or-miss with a three-valued element (1 = must be foreground, −1 = must be background,
//!   0 = ignored) is `erode(A, fg) ∧ erode(¬A, bg)`, OpenCV's `MORPH_HITMISS`, both erosions run
//!   by the van Herk / direct code of [`super::morphology`] with OpenCV's neutral border (pixels
//!   outside the image satisfy every condition).
//! - Thinning "golay" removes, in turn, the hits of the eight rotated Golay L elements
//!   (Gonzalez & Woods, *Digital Image Processing*, §9.5.5), `A ⊗ B = A − (A ⊛ B)`, until a
//!   whole round of eight changes nothing. The 3×3 hit-or-miss of each pass is a table lookup
//!   of the 8-neighbour code; pixels outside the image are background.
//! - Thinning "zhang_suen" is the two-sub-iteration parallel algorithm of Zhang & Suen (1984)
//!   as in OpenCV's `ximgproc::thinning(THINNING_ZHANGSUEN)`: the one-pixel frame of the image is
//!   never changed.
//! - Thickening is the complement of the thinning of the complement.
//! - Skeleton is Lantuéjoul's formula `S = ∪ₖ Sₖ`, `Sₖ = (A ⊖ kB) − (A ⊖ kB) ∘ B`, with set
//!   erosion, dilation and opening (pixels outside the image are background, so every image
//!   erodes to nothing and the loop ends).

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};

use super::morphology::{MorphBorder, Shape, StructuringElement, dilate, erode};

/// Largest hit-or-miss element side, px.
pub const MAX_ELEMENT: usize = 255;

/// The binary samples (0 or 1) of a gray u8 image, or an error naming the problem.
fn binary_input(image: &Image, op: &str) -> Result<Vec<u8>, OpError> {
    match (image.channels(), image.data()) {
        (Channels::Gray, PixelData::U8(data)) => Ok(data.iter().map(|&v| u8::from(v != 0)).collect()),
        _ => Err(OpError::new(format!(
            "{op} needs a binary gray u8 image (nonzero = foreground), got {} {}",
            image.channels().name(),
            image.depth().name()
        ))),
    }
}

/// A gray u8 image of `width × height` from 0/1 samples, written as 0/255.
fn binary_output(width: usize, height: usize, bits: &[u8]) -> Result<Image, OpError> {
    let data = bits.iter().map(|&b| if b != 0 { 255 } else { 0 }).collect();
    Image::from_u8(width, height, Channels::Gray, data).map_err(|e| OpError::new(e.to_string()))
}

/// A gray u8 image holding 0/255 from 0/1 bits (internal; sizes always agree).
fn mask_image(width: usize, height: usize, bits: &[u8]) -> Image {
    binary_output(width, height, bits)
        .unwrap_or_else(|_| Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap_or_else(|_| unreachable_image()))
}

/// Never used: an empty image always builds.
fn unreachable_image() -> Image {
    Image::zeros(0, 0, ocellus_engine::value::PixelFormat { channels: Channels::Gray, depth: ocellus_engine::value::Depth::U8 })
        .unwrap_or_else(|_| panic!("an empty image always builds"))
}
