//! libFuzzer target: arbitrary bytes as a `nrrd` volume file (`tetwave_fuzz::volume::check`).
#![no_main]

use libfuzzer_sys::fuzz_target;
use tetwave_fuzz::volume::{check, Target};

fuzz_target!(|data: &[u8]| {
    check(Target::Nrrd, data);
});
