//! Derivative and sharpening filters built on the separable passes: `filter.prewitt`,
//! `filter.laplacian`, `filter.log` (Laplacian of Gaussian), `filter.dog` (difference of
//! Gaussians) and `filter.unsharp` (unsharp mask).
//!
//! Prewitt and Laplacian follow `filter.sobel`'s conventions: f32 output with the input's
//! channels, exact for u8 input, `scale · result + delta`, and (for u8 input with 3-tap kernels)
//! the same exact integer path. LoG and DoG run as sums of separable passes on an f32 copy, never
//! as a dense 2-D kernel. Unsharp keeps the input's depth.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};

use super::border::{BorderMode, check_border_value};
use super::gaussian::{auto_ksize, gaussian_blur, gaussian_kernel, separable_filter};
use super::sobel::{SOBEL_KSIZES, check_common, deriv_kernel, derivative, derivative_sum, to_f32};

/// Largest sigma the Gaussian-based filters take, in px.
pub const MAX_SIGMA: f64 = 1000.0;

/// Largest explicit kernel size of LoG and DoG.
pub const MAX_KSIZE: u32 = 4095;

fn image_port(what: &str) -> Vec<PortSpec> {
    vec![PortSpec::new("image", PortType::Image, what)]
}

/// `a + b` sample by sample, for two f32 images of the same shape (`a` when they are not).
fn add_f32(a: Image, b: &Image) -> Image {
    combine_f32(a, b, |x, y| x + y)
}

/// `f(a, b)` sample by sample for two f32 images of the same shape, in place in `a`'s samples
/// (`a` unchanged when the shapes or depths differ).
fn combine_f32(a: Image, b: &Image, f: impl Fn(f32, f32) -> f32) -> Image {
    let (width, height, channels) = (a.width(), a.height(), a.channels());
    let Some(bv) = b.as_f32() else {
        return a;
    };
    let data = match a.into_data() {
        PixelData::F32(mut av) => {
            if av.len() == bv.len() {
                for (x, &y) in av.iter_mut().zip(bv) {
                    *x = f(*x, y);
                }
            }
            PixelData::F32(av)
        }
        other => other,
    };
    rebuild(width, height, channels, data, b)
}

/// The image of the given shape holding `data`; `fallback` (cloned) if they do not match, which
/// the callers rule out.
fn rebuild(
    width: usize,
    height: usize,
    channels: Channels,
    data: PixelData,
    fallback: &Image,
) -> Image {
    Image::new(width, height, channels, data).unwrap_or_else(|_| fallback.clone())
}

fn check_sigma(name: &str, sigma: f64) -> Result<(), String> {
    if sigma > 0.0 && sigma <= MAX_SIGMA {
        Ok(())
    } else {
        Err(format!(
            "`{name}` must be above 0 and at most {MAX_SIGMA} px, got {sigma}"
        ))
    }
}

fn check_ksize(ksize: u32) -> Result<(), String> {
    if ksize > MAX_KSIZE || (ksize != 0 && ksize.is_multiple_of(2)) {
        return Err(format!(
            "`ksize` must be odd and at most {MAX_KSIZE} (or 0 to derive it from sigma), got {ksize}"
        ));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Prewitt

params! {
    /// Parameters of `filter.prewitt`.
    pub struct PrewittParams {
        /// Order of the derivative along x: (dx, dy) must be (1, 0) or (0, 1).
        dx: u32 = 1 => [max = 1],
        /// Order of the derivative along y.
        dy: u32 = 0 => [max = 1],
        /// Factor applied to the derivative (output units per input unit).
        scale: f64 = 1.0,
        /// Value added after scaling, in output units.
        delta: f64 = 0.0,
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Prewitt derivative (`filter.prewitt`). See [`prewitt`].
#[derive(Debug, Clone, PartialEq)]
pub struct Prewitt {
    along_x: bool,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
}

impl Op for Prewitt {
    type Params = PrewittParams;
    const ID: &'static str = "filter.prewitt";
    const SUMMARY: &'static str = "First image derivative with the 3×3 Prewitt kernel.";
    const DOC: &'static str = r#"
Computes `scale · ∂I/∂x + delta` (dx = 1) or `scale · ∂I/∂y + delta` (dy = 1) with the 3×3
Prewitt kernel [−1 0 1; −1 0 1; −1 0 1] (separably: [−1 0 1] along the derivative, [1 1 1]
across it), so the x derivative of a ramp of slope s is 6·s. Output f32 with the input's
channels, exact for u8 input (same conventions and integer fast path as `filter.sobel`).

OpenCV has no Prewitt function; it equals `cv::filter2D(src, dst, CV_32F, kernel)` with the
kernel above. Reference: J. M. S. Prewitt, "Object enhancement and extraction", in Picture
Processing and Psychopictorics, 1970.

Example:
    "gx": (op: "filter.prewitt", inputs: { "image": "gray.image" }, params: (dx: 1, dy: 0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port("Image to differentiate, any pixel format.")
    }

    fn outputs() -> Vec<PortSpec> {
        image_port("The derivative as f32, same size and channels as the input.")
    }

    fn new(params: PrewittParams) -> Result<Self, String> {
        let PrewittParams {
            dx,
            dy,
            scale,
            delta,
            border,
            border_value,
        } = params;
        if !matches!((dx, dy), (1, 0) | (0, 1)) {
            return Err(format!(
                "(`dx`, `dy`) must be (1, 0) or (0, 1), got ({dx}, {dy})"
            ));
        }
        check_common(scale, delta, border, border_value)?;
        Ok(Prewitt {
            along_x: dx == 1,
            scale,
            delta,
            border,
            border_value,
        })
    }
}

impl Operator for Prewitt {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = prewitt(
            image,
            self.along_x,
            self.scale,
            self.delta,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Prewitt first derivative along x (`along_x`) or y, `scale · result + delta`, as an f32 image
/// with `image`'s size and channels.
pub fn prewitt(
    image: &Image,
    along_x: bool,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let difference = [-1.0, 0.0, 1.0];
    let mean = [1.0, 1.0, 1.0];
    let (kx, ky) = if along_x {
        (&difference, &mean)
    } else {
        (&mean, &difference)
    };
    derivative(image, kx, ky, scale, delta, border, border_value)
}

// ---------------------------------------------------------------------------------------------
// Laplacian

params! {
    /// Parameters of `filter.laplacian`.
    pub struct LaplacianParams {
        /// With `ksize` 1: 4 for [0 1 0; 1 −4 1; 0 1 0], 8 for [1 1 1; 1 −8 1; 1 1 1]. Larger
        /// sizes need 4 (the default).
        neighbours: u32 = 4 => [min = 4, max = 8],
        /// Kernel size: 1 (the 3×3 stencil above), or 3, 5, 7 px for the sum of the second
        /// Sobel derivatives of that size, as OpenCV. Default 1.
        ksize: u32 = 1 => [min = 1, max = 7, unit = "px"],
        /// Factor applied to the result (output units per input unit).
        scale: f64 = 1.0,
        /// Value added after scaling, in output units.
        delta: f64 = 0.0,
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Discrete Laplacian (`filter.laplacian`). See [`laplacian`].
#[derive(Debug, Clone, PartialEq)]
pub struct Laplacian {
    neighbours: u32,
    ksize: usize,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
}

impl Op for Laplacian {
    type Params = LaplacianParams;
    const ID: &'static str = "filter.laplacian";
    const SUMMARY: &'static str = "Discrete Laplacian ∂²I/∂x² + ∂²I/∂y² of an image.";
    const DOC: &'static str = r#"
Computes `scale · ∇²I + delta`. With `ksize` 1 the 3×3 stencil [0 1 0; 1 −4 1; 0 1 0]
(`neighbours: 4`, OpenCV's `Laplacian` with ksize 1) or [1 1 1; 1 −8 1; 1 1 1]
(`neighbours: 8`); with `ksize` 3, 5 or 7 the sum of the second Sobel derivatives of that size
along x and y (OpenCV's `Laplacian` with that ksize; for 3 that is [2 0 2; 0 −8 0; 2 0 2]).
Each part runs separably (the 4-neighbour stencil as [1 −2 1] along x plus along y, the
8-neighbour one as a 3×3 box sum minus 9·I), with the exact integer path for u8 input.

Output f32 with the input's channels for every input depth, exact for u8 input (OpenCV users
often ask for CV_16S, which this equals where CV_16S does not saturate). Channels are filtered
independently. Scale and delta are applied after the filter.

Reference: OpenCV `cv::Laplacian(src, dst, CV_32F, ksize, scale, delta, borderType)`.

Example:
    "lap": (op: "filter.laplacian", inputs: { "image": "gray.image" }, params: (neighbours: 8)),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port("Image to filter, any pixel format.")
    }

    fn outputs() -> Vec<PortSpec> {
        image_port("The Laplacian as f32, same size and channels as the input.")
    }

    fn new(params: LaplacianParams) -> Result<Self, String> {
        let LaplacianParams {
            neighbours,
            ksize,
            scale,
            delta,
            border,
            border_value,
        } = params;
        if neighbours != 4 && neighbours != 8 {
            return Err(format!("`neighbours` must be 4 or 8, got {neighbours}"));
        }
        if !SOBEL_KSIZES.contains(&ksize) {
            return Err(format!("`ksize` must be 1, 3, 5 or 7, got {ksize}"));
        }
        if neighbours == 8 && ksize != 1 {
            return Err(format!(
                "`neighbours` 8 exists only for `ksize` 1 (got ksize {ksize})"
            ));
        }
        check_common(scale, delta, border, border_value)?;
        Ok(Laplacian {
            neighbours,
            ksize: ksize as usize,
            scale,
            delta,
            border,
            border_value,
        })
    }
}

impl Operator for Laplacian {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = laplacian(
            image,
            self.neighbours == 8,
            self.ksize,
            self.scale,
            self.delta,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Discrete Laplacian, `scale · result + delta`, as an f32 image with `image`'s size and
/// channels: the 8-neighbour stencil when `eight` (and `ksize` 1), else the 4-neighbour stencil
/// for `ksize` 1 or the sum of second Sobel derivatives of size `ksize` (3, 5 or 7).
pub fn laplacian(
    image: &Image,
    eight: bool,
    ksize: usize,
    scale: f64,
    delta: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let ones = [1.0, 1.0, 1.0];
    let (second, identity, minus_nine) = ([1.0, -2.0, 1.0], [0.0, 1.0, 0.0], [0.0, -9.0, 0.0]);
    let (d2, smooth) = (deriv_kernel(ksize, 2), deriv_kernel(ksize, 0));
    let terms: [(&[f64], &[f64]); 2] = if ksize > 1 {
        [(&d2, &smooth), (&smooth, &d2)]
    } else if eight {
        // Box sum of the 3×3 neighbourhood minus nine times the centre.
        [(&ones, &ones), (&identity, &minus_nine)]
    } else {
        // [1 −2 1] along x plus along y; [0 1 0] keeps the 3-tap integer path.
        [(&second, &identity), (&identity, &second)]
    };
    derivative_sum(image, &terms, scale, delta, border, border_value)
}

// ---------------------------------------------------------------------------------------------
// Laplacian of Gaussian

params! {
    /// Parameters of `filter.log`.
    pub struct LogParams {
        /// Standard deviation of the Gaussian, in px (above 0).
        sigma: f64 = 1.0 => [min = 0.0, max = 1000.0, unit = "px"],
        /// Kernel size, odd; 0 chooses `round(6σ + 1) | 1` like `filter.gaussian`. Default 0.
        ksize: u32 = 0 => [max = 4095, unit = "px"],
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Laplacian of Gaussian (`filter.log`). See [`laplacian_of_gaussian`].
#[derive(Debug, Clone, PartialEq)]
pub struct Log {
    sigma: f64,
    ksize: usize,
    border: BorderMode,
    border_value: f64,
}

impl Op for Log {
    type Params = LogParams;
    const ID: &'static str = "filter.log";
    const SUMMARY: &'static str = "Laplacian of Gaussian (Marr–Hildreth edge operator).";
    const DOC: &'static str = r#"
Computes `∇²(G_σ ∗ I) = (G''_σ(x) G_σ(y) + G_σ(x) G''_σ(y)) ∗ I`, the Laplacian of the image
smoothed by a Gaussian of standard deviation `sigma`: its zero crossings are the edges of
Marr and Hildreth. Bright blobs of radius ≈ σ√2 give strong negative responses.

Method: two separable filters on an f32 copy, summed (never a dense 2-D kernel). G is OpenCV's
`getGaussianKernel` (samples of exp(−x²/2σ²) scaled to sum 1, `ksize` taps; 0 derives the
size as `filter.gaussian`); G'' holds the samples `(x² − σ²)/σ⁴ · G(x)` minus `(Σ G'')·G(x)`, so
that it sums to exactly zero: constant images give 0 and the response does not depend on the
image's mean. No σ² scale normalisation is applied (multiply by σ² for scale-normalised
responses). Output f32 with the input's channels.

OpenCV has no LoG function. Reference: D. Marr and E. Hildreth, "Theory of edge detection",
Proc. R. Soc. Lond. B 207, 1980.

Example:
    "log": (op: "filter.log", inputs: { "image": "gray.image" }, params: (sigma: 2.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port("Image to filter, any pixel format.")
    }

    fn outputs() -> Vec<PortSpec> {
        image_port("The LoG response as f32, same size and channels as the input.")
    }

    fn new(params: LogParams) -> Result<Self, String> {
        let LogParams {
            sigma,
            ksize,
            border,
            border_value,
        } = params;
        check_sigma("sigma", sigma)?;
        check_ksize(ksize)?;
        check_border_value(border, border_value)?;
        Ok(Log {
            sigma,
            ksize: if ksize == 0 {
                auto_ksize(sigma)
            } else {
                ksize as usize
            },
            border,
            border_value,
        })
    }
}

impl Operator for Log {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = laplacian_of_gaussian(
            image,
            self.sigma,
            self.ksize,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// The 1-D kernels of the LoG: `(G'', G)` with `ksize` taps (0: [`auto_ksize`]), G summing to
/// 1 and G'' to 0 (see [`Log`]).
pub fn log_kernels(sigma: f64, ksize: usize) -> (Vec<f64>, Vec<f64>) {
    let ksize = if ksize == 0 { auto_ksize(sigma) } else { ksize };
    let g = gaussian_kernel(ksize, sigma);
    let centre = (ksize as f64 - 1.0) * 0.5;
    let s2 = sigma * sigma;
    let mut d2: Vec<f64> = g
        .iter()
        .enumerate()
        .map(|(i, &w)| {
            let x = i as f64 - centre;
            (x * x - s2) / (s2 * s2) * w
        })
        .collect();
    let sum: f64 = d2.iter().sum();
    for (d, &w) in d2.iter_mut().zip(&g) {
        *d -= sum * w;
    }
    (d2, g)
}

/// Laplacian of Gaussian of `image` ([`Log`]), as f32 with `image`'s size and channels.
pub fn laplacian_of_gaussian(
    image: &Image,
    sigma: f64,
    ksize: usize,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let (d2, g) = log_kernels(sigma, ksize);
    let float = to_f32(image);
    let xx = separable_filter(&float, &d2, &g, border, border_value);
    let yy = separable_filter(&float, &g, &d2, border, border_value);
    add_f32(xx, &yy)
}

// ---------------------------------------------------------------------------------------------
// Difference of Gaussians

params! {
    /// Parameters of `filter.dog`.
    pub struct DogParams {
        /// Standard deviation of the narrower Gaussian, in px (above 0).
        sigma: f64 = 1.0 => [min = 0.0, max = 1000.0, unit = "px"],
        /// Ratio of the wider Gaussian's sigma to `sigma`, above 1. Default 1.6 (Marr and
        /// Hildreth's best approximation of the LoG).
        k: f64 = 1.6 => [min = 1.0, max = 100.0],
        /// Kernel size of both Gaussians, odd; 0 chooses `round(6kσ + 1) | 1` (the wider one's
        /// automatic size). Default 0.
        ksize: u32 = 0 => [max = 4095, unit = "px"],
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Difference of Gaussians (`filter.dog`). See [`difference_of_gaussians`].
#[derive(Debug, Clone, PartialEq)]
pub struct Dog {
    sigma: f64,
    k: f64,
    ksize: usize,
    border: BorderMode,
    border_value: f64,
}

impl Op for Dog {
    type Params = DogParams;
    const ID: &'static str = "filter.dog";
    const SUMMARY: &'static str = "Difference of Gaussians G(kσ) ∗ I − G(σ) ∗ I.";
    const DOC: &'static str = r#"
Computes `G_kσ ∗ I − G_σ ∗ I` as f32: a band-pass filter and, since ∂G/∂σ = σ∇²G, an
approximation of `(k − 1)σ² · ∇²G_σ ∗ I` (the scale-normalised Laplacian of Gaussian) that
Marr and Hildreth recommend with k = 1.6.

Method: two separable Gaussian blurs (kernels as OpenCV's `getGaussianKernel`, both with the
same `ksize` taps, by default the wider one's `round(6kσ + 1) | 1`) on an f32 copy, subtracted.
Output f32 with the input's channels.

Reference: D. Marr and E. Hildreth, "Theory of edge detection", Proc. R. Soc. Lond. B 207,
1980; with OpenCV: `GaussianBlur(I32F, kσ) − GaussianBlur(I32F, σ)`.

Example:
    "dog": (op: "filter.dog", inputs: { "image": "gray.image" }, params: (sigma: 1.0, k: 1.6)),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port("Image to filter, any pixel format.")
    }

    fn outputs() -> Vec<PortSpec> {
        image_port("The difference as f32, same size and channels as the input.")
    }

    fn new(params: DogParams) -> Result<Self, String> {
        let DogParams {
            sigma,
            k,
            ksize,
            border,
            border_value,
        } = params;
        check_sigma("sigma", sigma)?;
        if !(k > 1.0 && k <= 100.0) {
            return Err(format!("`k` must be above 1 and at most 100, got {k}"));
        }
        check_sigma("sigma · k", sigma * k)?;
        check_ksize(ksize)?;
        check_border_value(border, border_value)?;
        Ok(Dog {
            sigma,
            k,
            ksize: if ksize == 0 {
                auto_ksize(k * sigma)
            } else {
                ksize as usize
            },
            border,
            border_value,
        })
    }
}

impl Operator for Dog {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = difference_of_gaussians(
            image,
            self.sigma,
            self.k,
            self.ksize,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// `G_kσ ∗ I − G_σ ∗ I` ([`Dog`]) with both kernels `ksize` taps (0: [`auto_ksize`] of `kσ`),
/// as f32 with `image`'s size and channels.
pub fn difference_of_gaussians(
    image: &Image,
    sigma: f64,
    k: f64,
    ksize: usize,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let ksize = if ksize == 0 {
        auto_ksize(k * sigma)
    } else {
        ksize
    };
    let float = to_f32(image);
    let wide = gaussian_blur(
        &float,
        k * sigma,
        k * sigma,
        ksize,
        ksize,
        border,
        border_value,
    );
    let narrow = gaussian_blur(&float, sigma, sigma, ksize, ksize, border, border_value);
    combine_f32(wide, &narrow, |a, b| a - b)
}

// ---------------------------------------------------------------------------------------------
// Unsharp mask

params! {
    /// Parameters of `filter.unsharp`.
    pub struct UnsharpParams {
        /// Standard deviation of the Gaussian blur, in px (above 0); its size is
        /// `round(6σ + 1) | 1`.
        sigma: f64 = 1.0 => [min = 0.0, max = 1000.0, unit = "px"],
        /// Strength: out = I + amount · (I − blur). Default 1.0; 0 returns the input.
        amount: f64 = 1.0 => [min = 0.0, max = 100.0],
        /// Smallest |I − blur| that is sharpened, in the image's units (gray levels for u8);
        /// smaller differences are left unchanged. Default 0 (sharpen everywhere).
        threshold: f64 = 0.0 => [min = 0.0, unit = "gray levels"],
        /// How pixels outside the image are read.
        border: BorderMode = BorderMode::Reflect101,
        /// Sample value read outside the image with border "constant", in the image's units.
        border_value: f64 = 0.0,
    }
}

/// Unsharp mask (`filter.unsharp`). See [`unsharp_mask`].
#[derive(Debug, Clone, PartialEq)]
pub struct Unsharp {
    sigma: f64,
    amount: f64,
    threshold: f64,
    border: BorderMode,
    border_value: f64,
}

impl Op for Unsharp {
    type Params = UnsharpParams;
    const ID: &'static str = "filter.unsharp";
    const SUMMARY: &'static str = "Sharpens an image with an unsharp mask.";
    const DOC: &'static str = r#"
Computes `out = I + amount · (I − G_σ ∗ I)` where `|I − G_σ ∗ I| ≥ threshold`, and `out = I`
elsewhere (the threshold keeps noise in flat areas from being amplified). The blur is a
Gaussian (`filter.gaussian`'s kernel, `round(6σ + 1) | 1` taps) computed in f32; the result is
rounded to nearest and saturated for u8 and u16, so the output has the input's pixel format.

Reference: the photographic unsharp mask; with OpenCV, `addWeighted(I, 1 + amount,
GaussianBlur(I, σ), −amount, 0)` for threshold 0 (OpenCV blurs u8 in 8-bit fixed point, so
results may differ by one level).

Example:
    "sharp": (op: "filter.unsharp", inputs: { "image": "photo.image" }, params: (sigma: 2.0, amount: 0.8, threshold: 3)),
"#;

    fn inputs() -> Vec<PortSpec> {
        image_port("Image to sharpen, any pixel format.")
    }

    fn outputs() -> Vec<PortSpec> {
        image_port("The sharpened image, same size and pixel format as the input.")
    }

    fn new(params: UnsharpParams) -> Result<Self, String> {
        let UnsharpParams {
            sigma,
            amount,
            threshold,
            border,
            border_value,
        } = params;
        check_sigma("sigma", sigma)?;
        if !(0.0..=100.0).contains(&amount) {
            return Err(format!("`amount` must be between 0 and 100, got {amount}"));
        }
        if !(threshold >= 0.0 && threshold.is_finite()) {
            return Err(format!(
                "`threshold` must be finite and at least 0, got {threshold}"
            ));
        }
        check_border_value(border, border_value)?;
        Ok(Unsharp {
            sigma,
            amount,
            threshold,
            border,
            border_value,
        })
    }
}

impl Operator for Unsharp {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let out = unsharp_mask(
            image,
            self.sigma,
            self.amount,
            self.threshold,
            self.border,
            self.border_value,
        );
        Ok(Outputs::new().with("image", Value::image(out)))
    }
}

/// Unsharp mask ([`Unsharp`]) of `image`, in `image`'s pixel format.
pub fn unsharp_mask(
    image: &Image,
    sigma: f64,
    amount: f64,
    threshold: f64,
    border: BorderMode,
    border_value: f64,
) -> Image {
    let float = to_f32(image);
    let blurred = gaussian_blur(&float, sigma, sigma, 0, 0, border, border_value);
    let (amount, threshold) = (amount as f32, threshold as f32);
    let sharp = combine_f32(float, &blurred, |x, b| {
        let detail = x - b;
        if detail.abs() >= threshold {
            x + amount * detail
        } else {
            x
        }
    });
    let (width, height, channels) = (image.width(), image.height(), image.channels());
    let values = sharp.as_f32().unwrap_or(&[]);
    let data = match image.data() {
        PixelData::U8(_) => {
            PixelData::U8(values.iter().map(|&v| v.round_ties_even() as u8).collect())
        }
        PixelData::U16(_) => {
            PixelData::U16(values.iter().map(|&v| v.round_ties_even() as u16).collect())
        }
        PixelData::F32(_) => PixelData::F32(values.to_vec()),
    };
    Image::new(width, height, channels, data).unwrap_or_else(|_| image.clone())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::convolve::{ConvolveOptions, Kernel, OutputDepth, correlate_dense};
    use crate::filter::test_support::{MODES, random_u8, randoms};
    use proptest::prelude::*;

    fn samples(image: &Image) -> Vec<f64> {
        match image.data() {
            PixelData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            PixelData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }

    fn gray_f32(w: usize, h: usize, f: impl Fn(usize, usize) -> f64) -> Image {
        let data = (0..w * h).map(|k| f(k % w, k / w) as f32).collect();
        Image::from_f32(w, h, Channels::Gray, data).unwrap()
    }

    /// The dense 2-D kernel `Σ column ⊗ row` over the given pairs.
    fn dense(pairs: &[(&[f64], &[f64])]) -> Kernel {
        let (w, h) = (pairs[0].1.len(), pairs[0].0.len());
        let mut weights = vec![0.0; w * h];
        for (column, row) in pairs {
            for j in 0..h {
                for i in 0..w {
                    weights[j * w + i] += column[j] * row[i];
                }
            }
        }
        Kernel {
            width: w,
            height: h,
            weights,
        }
    }

    /// Direct 2-D correlation as f32 (the reference of `filter.convolve`'s tests).
    fn direct(image: &Image, kernel: &Kernel, border: BorderMode, value: f64) -> Vec<f64> {
        let options = ConvolveOptions {
            border,
            border_value: value,
            depth: OutputDepth::F32,
            ..ConvolveOptions::centred(kernel)
        };
        samples(&correlate_dense(image, kernel, &options))
    }

    fn constant_for(mode: BorderMode) -> f64 {
        if mode == BorderMode::Constant {
            31.0
        } else {
            0.0
        }
    }

    #[test]
    fn prewitt_ramp_and_kernel() {
        let (w, h, slope) = (10, 5, 4u8);
        let data = (0..w * h).map(|k| (k % w) as u8 * slope).collect();
        let ramp = Image::from_u8(w, h, Channels::Gray, data).unwrap();
        let gx = prewitt(&ramp, true, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        assert_eq!(gx.as_f32().unwrap()[w + 4], 6.0 * f32::from(slope));
        let gy = prewitt(&ramp, false, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        assert!(gy.as_f32().unwrap().iter().all(|&v| v == 0.0));
        let image = random_u8(9, 7, Channels::Rgb, 3);
        let kx = dense(&[(&[1.0, 1.0, 1.0], &[-1.0, 0.0, 1.0])]);
        let ky = dense(&[(&[-1.0, 0.0, 1.0], &[1.0, 1.0, 1.0])]);
        for mode in MODES {
            let v = constant_for(mode);
            let gx = prewitt(&image, true, 1.0, 0.0, mode, v);
            assert_eq!(samples(&gx), direct(&image, &kx, mode, v), "{mode:?}");
            let gy = prewitt(&image, false, 1.0, 0.0, mode, v);
            assert_eq!(samples(&gy), direct(&image, &ky, mode, v), "{mode:?}");
        }
        let scaled = prewitt(&ramp, true, 0.5, 1.0, BorderMode::Reflect101, 0.0);
        assert_eq!(scaled.as_f32().unwrap()[w + 4], 13.0);
    }

    #[test]
    fn laplacian_matches_dense_stencils() {
        let four = Kernel::from_rows(&[
            vec![0.0, 1.0, 0.0],
            vec![1.0, -4.0, 1.0],
            vec![0.0, 1.0, 0.0],
        ])
        .unwrap();
        let eight = Kernel::from_rows(&[
            vec![1.0, 1.0, 1.0],
            vec![1.0, -8.0, 1.0],
            vec![1.0, 1.0, 1.0],
        ])
        .unwrap();
        let three = Kernel::from_rows(&[
            vec![2.0, 0.0, 2.0],
            vec![0.0, -8.0, 0.0],
            vec![2.0, 0.0, 2.0],
        ])
        .unwrap();
        let (d2, s) = (deriv_kernel(5, 2), deriv_kernel(5, 0));
        let five = dense(&[(&s, &d2), (&d2, &s)]);
        for (w, h) in [(11, 8), (1, 1), (2, 5)] {
            let image = random_u8(w, h, Channels::Rgba, (w * h) as u64);
            for mode in MODES {
                let v = constant_for(mode);
                for (eight_n, ksize, kernel) in [
                    (false, 1, &four),
                    (true, 1, &eight),
                    (false, 3, &three),
                    (false, 5, &five),
                ] {
                    let got = laplacian(&image, eight_n, ksize, 1.0, 0.0, mode, v);
                    assert_eq!(
                        samples(&got),
                        direct(&image, kernel, mode, v),
                        "{w}×{h} {mode:?} ksize {ksize} eight {eight_n}"
                    );
                }
            }
        }
    }

    #[test]
    fn laplacian_integer_path_equals_float_path() {
        // u8 input takes the one-pass integer path, its f32 copy the general one.
        let image = random_u8(37, 23, Channels::Rgb, 11);
        let float = to_f32(&image);
        for mode in MODES {
            let v = constant_for(mode);
            for (eight, ksize) in [(false, 1), (true, 1), (false, 3), (false, 5)] {
                for (scale, delta) in [(1.0, 0.0), (0.3, -2.5)] {
                    let run = |i: &Image| laplacian(i, eight, ksize, scale, delta, mode, v);
                    assert_eq!(run(&image), run(&float), "{mode:?} {eight} {ksize}");
                }
            }
        }
    }

    #[test]
    fn laplacian_matches_opencv_values() {
        // cv2.Laplacian(img, cv2.CV_32F, ksize=k) on img = (7·x + 3·y²) mod 256 (u8, 6×4),
        // default border (reflect_101).
        let image = Image::from_u8(
            6,
            4,
            Channels::Gray,
            (0..24)
                .map(|k| ((7 * (k % 6) + 3 * (k / 6) * (k / 6)) % 256) as u8)
                .collect(),
        )
        .unwrap();
        let expected: [(usize, [f64; 24]); 3] = [
            (
                1,
                [
                    20.0, 6.0, 6.0, 6.0, 6.0, -8.0, 20.0, 6.0, 6.0, 6.0, 6.0, -8.0, 20.0, 6.0, 6.0,
                    6.0, 6.0, -8.0, -16.0, -30.0, -30.0, -30.0, -30.0, -44.0,
                ],
            ),
            (
                3,
                [
                    80.0, 24.0, 24.0, 24.0, 24.0, -32.0, 80.0, 24.0, 24.0, 24.0, 24.0, -32.0, 80.0,
                    24.0, 24.0, 24.0, 24.0, -32.0, -64.0, -120.0, -120.0, -120.0, -120.0, -176.0,
                ],
            ),
            (
                5,
                [
                    832.0, 608.0, 384.0, 384.0, 160.0, -64.0, 832.0, 608.0, 384.0, 384.0, 160.0,
                    -64.0, 256.0, 32.0, -192.0, -192.0, -416.0, -640.0, -320.0, -544.0, -768.0,
                    -768.0, -992.0, -1216.0,
                ],
            ),
        ];
        for (ksize, values) in expected {
            let got = laplacian(&image, false, ksize, 1.0, 0.0, BorderMode::Reflect101, 0.0);
            assert_eq!(samples(&got), values, "ksize {ksize}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn log_kernel_sums_to_zero(sigma in 0.3f64..20.0, extra in 0usize..4) {
            let ksize = auto_ksize(sigma) + 2 * extra;
            let (d2, g) = log_kernels(sigma, ksize);
            prop_assert_eq!(d2.len(), ksize);
            prop_assert!((g.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            prop_assert!(d2.iter().sum::<f64>().abs() < 1e-12);
            // Symmetric, negative at the centre.
            prop_assert!(d2.iter().zip(d2.iter().rev()).all(|(a, b)| (a - b).abs() < 1e-15));
            prop_assert!(d2[ksize / 2] < 0.0);
        }

        #[test]
        fn log_of_constant_image_is_zero(sigma in 0.5f64..4.0, level in 0u8..=255, mode in 1usize..5) {
            let image = Image::from_u8(13, 9, Channels::Gray, vec![level; 13 * 9]).unwrap();
            let out = laplacian_of_gaussian(&image, sigma, 0, MODES[mode], 0.0);
            prop_assert!(out.as_f32().unwrap().iter().all(|v| v.abs() < 1e-3));
        }
    }

    #[test]
    fn log_equals_dense_kernel() {
        let image = random_u8(17, 12, Channels::Gray, 5);
        for (sigma, ksize) in [(1.0, 0), (1.4, 5), (0.8, 9)] {
            let (d2, g) = log_kernels(sigma, ksize);
            let kernel = dense(&[(&g, &d2), (&d2, &g)]);
            for mode in MODES {
                let v = constant_for(mode);
                let got = samples(&laplacian_of_gaussian(&image, sigma, ksize, mode, v));
                for (a, b) in got.iter().zip(direct(&image, &kernel, mode, v)) {
                    assert!((a - b).abs() < 1e-3, "σ {sigma} {mode:?}: {a} vs {b}");
                }
            }
        }
    }

    #[test]
    fn log_of_paraboloid_is_four() {
        // ∇²(x² + y²) = 4 everywhere; check away from the border.
        let image = gray_f32(41, 41, |x, y| {
            let (x, y) = (x as f64 - 20.0, y as f64 - 20.0);
            x * x + y * y
        });
        let out = laplacian_of_gaussian(&image, 2.0, 25, BorderMode::Reflect101, 0.0);
        let v = out.as_f32().unwrap()[20 * 41 + 20];
        assert!((v - 4.0).abs() < 0.05, "{v}");
    }

    #[test]
    fn dog_approximates_scaled_log() {
        // G(kσ) − G(σ) ≈ (k − 1)σ² ∇²G for k near 1, on a smooth blob.
        let image = gray_f32(61, 61, |x, y| {
            let (x, y) = (x as f64 - 30.0, y as f64 - 30.0);
            100.0 * (-(x * x + y * y) / 50.0).exp()
        });
        let (sigma, k) = (2.0, 1.01);
        let ksize = 25;
        let dog = samples(&difference_of_gaussians(
            &image,
            sigma,
            k,
            ksize,
            BorderMode::Reflect101,
            0.0,
        ));
        let log = samples(&laplacian_of_gaussian(
            &image,
            sigma,
            ksize,
            BorderMode::Reflect101,
            0.0,
        ));
        let scale = (k - 1.0) * sigma * sigma;
        let peak = log.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (a, b) in dog.iter().zip(&log) {
            assert!((a / scale - b).abs() < 0.03 * peak, "{} vs {b}", a / scale);
        }
    }

    #[test]
    fn dog_of_constant_is_zero_and_formats() {
        let image = Image::from_u16(9, 8, Channels::Rgb, vec![4000; 9 * 8 * 3]).unwrap();
        let out = difference_of_gaussians(&image, 1.0, 1.6, 0, BorderMode::Wrap, 0.0);
        assert_eq!(out.channels(), Channels::Rgb);
        assert!(out.as_f32().unwrap().iter().all(|v| v.abs() < 1e-2));
    }

    #[test]
    fn unsharp_cases() {
        let image = random_u8(15, 11, Channels::Rgb, 2);
        let same = unsharp_mask(&image, 1.5, 0.0, 0.0, BorderMode::Reflect101, 0.0);
        assert_eq!(same, image);
        let same = unsharp_mask(&image, 1.5, 2.0, 1000.0, BorderMode::Reflect101, 0.0);
        assert_eq!(same, image);
        let flat = Image::from_u8(7, 7, Channels::Gray, vec![77; 49]).unwrap();
        assert_eq!(
            unsharp_mask(&flat, 2.0, 3.0, 0.0, BorderMode::Clamp, 0.0),
            flat
        );
        // A step edge overshoots on both sides and saturates.
        let step =
            Image::from_u8(8, 1, Channels::Gray, vec![0, 0, 0, 0, 255, 255, 255, 255]).unwrap();
        let sharp = unsharp_mask(&step, 1.0, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        assert_eq!(sharp.as_u8().unwrap(), &[0, 0, 0, 0, 255, 255, 255, 255]);
        let step = Image::from_u8(
            8,
            1,
            Channels::Gray,
            vec![50, 50, 50, 50, 200, 200, 200, 200],
        )
        .unwrap();
        let sharp = unsharp_mask(&step, 1.0, 1.0, 0.0, BorderMode::Reflect101, 0.0);
        let s = sharp.as_u8().unwrap();
        assert!(s[3] < 50 && s[4] > 200, "{s:?}");
        assert_eq!((s[0], s[7]), (50, 50 + 150));
        // f32: exactly I + amount · (I − blur), with the threshold applied per sample.
        let image = gray_f32(9, 6, |x, y| ((x * 7 + y * 3) % 5) as f64);
        let blur = samples(&gaussian_blur(
            &image,
            1.0,
            1.0,
            0,
            0,
            BorderMode::Reflect,
            0.0,
        ));
        let out = samples(&unsharp_mask(
            &image,
            1.0,
            0.5,
            0.5,
            BorderMode::Reflect,
            0.0,
        ));
        for ((&x, &b), &o) in samples(&image).iter().zip(&blur).zip(&out) {
            let e = if (x - b).abs() >= 0.5 {
                x + 0.5 * (x - b)
            } else {
                x
            };
            assert!((o - e).abs() < 1e-5);
        }
    }

    #[test]
    fn empty_and_tiny_images() {
        for (w, h) in [(0, 0), (3, 0)] {
            let empty = Image::from_u8(w, h, Channels::Gray, vec![]).unwrap();
            let b = BorderMode::Reflect101;
            for out in [
                prewitt(&empty, true, 1.0, 0.0, b, 0.0),
                laplacian(&empty, true, 1, 1.0, 0.0, b, 0.0),
                laplacian(&empty, false, 5, 1.0, 0.0, b, 0.0),
                laplacian_of_gaussian(&empty, 1.0, 0, b, 0.0),
                difference_of_gaussians(&empty, 1.0, 1.6, 0, b, 0.0),
                unsharp_mask(&empty, 1.0, 1.0, 0.0, b, 0.0),
            ] {
                assert_eq!((out.width(), out.height()), (w, h));
            }
        }
        let one = Image::from_f32(1, 1, Channels::Gray, vec![3.0]).unwrap();
        let b = BorderMode::Reflect101;
        assert_eq!(
            laplacian(&one, false, 1, 1.0, 0.0, b, 0.0)
                .as_f32()
                .unwrap(),
            &[0.0]
        );
        assert!(
            laplacian_of_gaussian(&one, 1.0, 0, b, 0.0)
                .as_f32()
                .unwrap()[0]
                .abs()
                < 1e-5
        );
        let sharp = unsharp_mask(&one, 1.0, 1.0, 0.0, b, 0.0);
        assert!((sharp.as_f32().unwrap()[0] - 3.0).abs() < 1e-5);
    }

    #[test]
    fn linear_for_f32() {
        let a = gray_f32(19, 13, |x, y| randoms((x * 13 + y) as u64, 1)[0]);
        let b = gray_f32(19, 13, |x, y| randoms((x * 17 + y + 999) as u64, 1)[0]);
        let mix = gray_f32(19, 13, |x, y| {
            2.0 * samples(&a)[y * 19 + x] - 0.5 * samples(&b)[y * 19 + x]
        });
        type Filter = fn(&Image) -> Image;
        let filters: [Filter; 3] = [
            |i| laplacian_of_gaussian(i, 1.2, 0, BorderMode::Reflect, 0.0),
            |i| difference_of_gaussians(i, 1.0, 1.6, 0, BorderMode::Reflect, 0.0),
            |i| laplacian(i, true, 1, 1.0, 0.0, BorderMode::Reflect, 0.0),
        ];
        for f in filters {
            let (fa, fb, fm) = (samples(&f(&a)), samples(&f(&b)), samples(&f(&mix)));
            for t in 0..fm.len() {
                assert!((fm[t] - (2.0 * fa[t] - 0.5 * fb[t])).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn new_checks_params() {
        assert!(Laplacian::new(LaplacianParams::default()).is_ok());
        let lap = |neighbours, ksize| LaplacianParams {
            neighbours,
            ksize,
            ..LaplacianParams::default()
        };
        assert!(Laplacian::new(lap(8, 1)).is_ok());
        assert!(Laplacian::new(lap(6, 1)).is_err());
        assert!(Laplacian::new(lap(8, 3)).is_err());
        assert!(Laplacian::new(lap(4, 7)).is_ok());
        assert!(Laplacian::new(lap(4, 4)).is_err());
        assert!(Prewitt::new(PrewittParams::default()).is_ok());
        let pw = PrewittParams {
            dx: 1,
            dy: 1,
            ..PrewittParams::default()
        };
        assert!(Prewitt::new(pw).is_err());
        assert!(Log::new(LogParams::default()).is_ok());
        for (sigma, ksize) in [(0.0, 0), (f64::NAN, 0), (1.0, 4), (1.0, 5000)] {
            let p = LogParams {
                sigma,
                ksize,
                ..LogParams::default()
            };
            assert!(Log::new(p).is_err(), "{sigma} {ksize}");
        }
        assert!(Dog::new(DogParams::default()).is_ok());
        for k in [1.0, 0.5, f64::INFINITY] {
            let p = DogParams {
                k,
                ..DogParams::default()
            };
            assert!(Dog::new(p).is_err());
        }
        assert!(Unsharp::new(UnsharpParams::default()).is_ok());
        for (amount, threshold) in [
            (-1.0, 0.0),
            (f64::NAN, 0.0),
            (1.0, -1.0),
            (1.0, f64::INFINITY),
        ] {
            let p = UnsharpParams {
                amount,
                threshold,
                ..UnsharpParams::default()
            };
            assert!(Unsharp::new(p).is_err());
        }
        let p = UnsharpParams {
            border_value: 5.0,
            ..UnsharpParams::default()
        };
        assert!(Unsharp::new(p).is_err());
    }
}
