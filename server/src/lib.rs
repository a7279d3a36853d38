//! # tetwave-server
//!
//! The server side of tetwave, one module per pipeline stage:
//! [`resample`] (volume → semi-regular mesh samples), [`analysis`] (lifting → detail nodes),
//! [`store`] (coefficients on disk, random access by node id) and [`prepare`] (the three in a row, as
//! `tetwave-server prepare` runs them).

pub mod analysis;
pub mod prepare;
pub mod resample;
pub mod store;
