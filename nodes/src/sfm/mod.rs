//! Structure from motion and dense 3-D: stereo matching, reconstruction.

pub mod stereo;
