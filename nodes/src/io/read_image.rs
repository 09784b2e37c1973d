//! `io.read_image`: decode an image file.

use std::path::PathBuf;

use ocellus_engine::image_io::{DecodeLimits, read_image};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

ocellus_engine::params! {
    /// Parameters of [`ReadImage`].
    pub struct ReadImageParams {
        /// The image file; relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
        /// Largest image accepted, in pixels (a guard against decompression bombs: the header is
        /// checked before any pixel is decoded). The run's `--max-image-pixels` caps it too.
        max_pixels: u64 = 1 << 28 => [min = 1],
    }
}

/// Reads PNG (8/16-bit), JPEG, PNM (PGM/PPM/PAM), TIFF, PFM and OpenEXR files into gray/rgb/rgba images of
/// u8, u16 or f32 samples, without lossy conversion. The format is recognised by content.
pub struct ReadImage {
    params: ReadImageParams,
}

impl Operator for ReadImage {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let run = DecodeLimits::default();
        let limits = DecodeLimits {
            max_pixels: self.params.max_pixels.min(run.max_pixels),
            ..run
        };
        let image =
            read_image(&self.params.path, &limits).map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }

    /// The file's contents decide the result, so they are part of the cache key.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let bytes = ocellus_engine::limits::read_file(&self.params.path)
            .map_err(|e| OpError::io(&self.params.path, e))?;
        Ok(ocellus_engine::cache::content_hash(&bytes).to_vec())
    }
}

impl Op for ReadImage {
    type Params = ReadImageParams;
    const ID: &'static str = "io.read_image";
    const SUMMARY: &'static str = "Read an image file (PNG, JPEG, PNM, TIFF, PFM, EXR).";
    const DOC: &'static str = "Decodes by content (magic bytes), keeping bit depth: 8-bit → u8, \
        16-bit → u16, PFM/float TIFF/EXR → f32 (one EXR channel → gray, half floats widened). Gray+alpha becomes rgba. Dimensions are checked \
        against `max_pixels` before decoding. Corrupt or truncated files are errors, never \
        partial images. Example: `(op: \"io.read_image\", params: (path: \"data/card.png\"))`.";

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "The decoded image.",
        )]
    }

    fn new(params: ReadImageParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadImage { params })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::image_io::write_image;
    use ocellus_engine::{Channels, Image, Params};

    fn ctx() -> RunContext {
        RunContext {
            node: "read".into(),
            threads: 1,
            element: None,
        }
    }

    #[test]
    fn reads_what_was_written_and_fingerprints_content() {
        let dir = std::env::temp_dir().join(format!("ocellus-read-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.png");
        let image = Image::from_u8(3, 2, Channels::Gray, vec![0, 50, 100, 150, 200, 250]).unwrap();
        write_image(&path, &image).unwrap();
        let op = ReadImage::new(ReadImageParams {
            path: path.clone(),
            ..ReadImageParams::default()
        })
        .unwrap();
        let mut out = op.run(&ctx(), &Inputs::new(&[], &[])).unwrap();
        assert_eq!(out.take("image"), Some(Value::image(image)));
        let before = op.fingerprint().unwrap();
        let other = Image::from_u8(3, 2, Channels::Gray, vec![1; 6]).unwrap();
        write_image(&path, &other).unwrap();
        assert_ne!(op.fingerprint().unwrap(), before);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn missing_and_corrupt_files_are_errors() {
        let op = ReadImage::new(ReadImageParams {
            path: "/nonexistent/ocellus.png".into(),
            ..ReadImageParams::default()
        })
        .unwrap();
        assert!(op.fingerprint().is_err());
        assert!(op.run(&ctx(), &Inputs::new(&[], &[])).is_err());
        let dir = std::env::temp_dir().join(format!("ocellus-corrupt-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("bad.png");
        std::fs::write(&path, b"\x89PNG\r\n\x1a\nnot really").unwrap();
        let op = ReadImage::new(ReadImageParams {
            path,
            ..ReadImageParams::default()
        })
        .unwrap();
        let err = op
            .run(&ctx(), &Inputs::new(&[], &[]))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("bad.png"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn path_is_required() {
        assert!(ReadImage::new(ReadImageParams::default()).is_err());
        assert_eq!(ReadImageParams::schema()[0].name, "path");
    }
}
