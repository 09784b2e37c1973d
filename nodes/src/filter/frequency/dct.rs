//! `filter.dct`.
