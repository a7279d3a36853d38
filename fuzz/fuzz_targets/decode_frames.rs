//! libFuzzer target: arbitrary bytes into `decode_client`, `decode_server` and `frame_len`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    tetwave_fuzz::check(data);
});
