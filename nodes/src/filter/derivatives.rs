//! Derivative and sharpening filters built on the separable passes.
