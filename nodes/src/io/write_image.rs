//! `io.write_image`: encode an image to a file, atomically.

use std::path::PathBuf;

use ocellus_engine::image_io::write_image;
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

ocellus_engine::params! {
    /// Parameters of [`WriteImage`].
    pub struct WriteImageParams {
        /// Destination; the extension picks the format (png, jpg, pgm/ppm/pnm, tif, pfm, exr).
        /// Relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
    }
}

/// Writes an image file. The file appears complete or not at all (temporary file + rename).
/// PNG holds u8 and u16 (16-bit PNG); PFM holds f32 gray/rgb; EXR holds f32 gray/rgb/rgba; JPEG holds u8 gray/rgb.
pub struct WriteImage {
    params: WriteImageParams,
}

impl Operator for WriteImage {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let path = match ctx.element {
            // A mapped writer gets one file per element: `frame.png` → `frame_0003.png`.
            Some(k) => numbered(&self.params.path, k),
            None => self.params.path.clone(),
        };
        write_image(&path, image).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("path", Value::Text(path.to_string_lossy().into())))
    }
}

/// `dir/name.ext` → `dir/name_000k.ext`.
pub(crate) fn numbered(path: &std::path::Path, k: usize) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match path.extension() {
        Some(ext) => format!("{stem}_{k:04}.{}", ext.to_string_lossy()),
        None => format!("{stem}_{k:04}"),
    };
    path.with_file_name(name)
}

impl Op for WriteImage {
    type Params = WriteImageParams;
    const ID: &'static str = "io.write_image";
    const SUMMARY: &'static str =
        "Write an image file (PNG, JPEG, PNM, TIFF, PFM, EXR), atomically.";
    const DOC: &'static str = "Encodes by the path's extension and writes through a temporary file \
        renamed into place, so readers never see a partial file. Runs whenever the graph runs \
        without an output selection (it is a side effect), and is never served from the cache. \
        When mapped over a list, element k goes to `NAME_000k.EXT`. Example: \
        `(op: \"io.write_image\", inputs: { \"image\": \"blur.image\" }, params: (path: \"out/blur.png\"))`.";
    const SIDE_EFFECTS: bool = true;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The image to write.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new("path", PortType::Text, "The file written.")]
    }

    fn new(params: WriteImageParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        let ext = params
            .path
            .extension()
            .map(|e| e.to_string_lossy().to_lowercase());
        let known = ext
            .as_deref()
            .is_some_and(|e| ocellus_engine::image_io::ImageFormat::from_extension(e).is_some());
        if !known {
            return Err(format!(
                "cannot tell the image format of `{}`: use .png, .jpg, .pgm/.ppm/.pnm, .tif, .pfm or .exr",
                params.path.display()
            ));
        }
        Ok(WriteImage { params })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::image_io::{DecodeLimits, read_image};
    use ocellus_engine::{Channels, Image};

    #[test]
    fn writes_and_numbers_mapped_elements() {
        let dir = std::env::temp_dir().join(format!("ocellus-write-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let op = WriteImage::new(WriteImageParams {
            path: dir.join("out.png"),
        })
        .unwrap();
        let image = Value::image(Image::from_u8(2, 2, Channels::Rgb, (0..12).collect()).unwrap());
        let specs = WriteImage::inputs();
        let values = [Some(image.clone())];
        for element in [None, Some(3)] {
            let ctx = RunContext {
                node: "w".into(),
                threads: 1,
                element,
            };
            let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
            let Some(Value::Text(path)) = out.take("path") else {
                panic!("no path")
            };
            let back = read_image(std::path::Path::new(&*path), &DecodeLimits::default()).unwrap();
            assert_eq!(Value::image(back), image);
        }
        assert!(dir.join("out_0003.png").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn unknown_extension_is_rejected_at_load() {
        let err = WriteImage::new(WriteImageParams {
            path: "x.bmpz".into(),
        })
        .err()
        .unwrap();
        assert!(err.contains(".png"), "{err}");
        assert!(WriteImage::new(WriteImageParams::default()).is_err());
    }
}
