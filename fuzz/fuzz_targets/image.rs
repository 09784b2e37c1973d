#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| ocellus_nodes::fuzz::image(data));
