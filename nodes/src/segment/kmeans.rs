//! `segment.kmeans` (in progress).
