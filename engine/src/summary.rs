//! stub
use crate::value::Value;
pub fn summarize_outputs(o: &[(String, Value)]) -> String {
    format!("{o:?}")
}
