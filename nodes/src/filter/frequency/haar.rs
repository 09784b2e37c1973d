//! `filter.haar`.
