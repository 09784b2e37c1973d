//! `segment.watershed` (in progress).
