//! `segment.region_grow` (in progress).
