//! # tetwave-server
//!
//! The server side of tetwave, one module per pipeline stage:
//! [`resample`] (volume → semi-regular mesh samples),
//! [`analysis`] (lifting → detail nodes), [`prepare`] (import, resampling and analysis in a row, then the store written
//! through `tetwave-store`, as `tetwave-server prepare` runs them), [`stream`] (`tetwave-server
//! serve`: HTTP endpoints and the progressive WebSocket stream) and [`render_service`] (fallback
//! images and the viewer page). Reading the user's mesh files and choosing its scalar is the
//! `tetwave-import` crate, which `tetwave render <mesh>` shares.

pub mod analysis;
pub mod prepare;
pub mod render_service;
pub mod resample;
pub mod stream;
