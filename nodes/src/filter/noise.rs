//! `filter.noise`.
