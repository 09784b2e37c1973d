//! `segment.graph_cut` (in progress).
