//! Built-in operators.
