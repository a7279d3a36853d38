//! # tetwave-server
//!
//! The server side of tetwave, one module per pipeline stage:
//! [`import`] (reading the user's mesh files), [`resample`] (volume → semi-regular mesh samples),
//! [`analysis`] (lifting → detail nodes), [`prepare`] (the three in a row, then the store written
//! through `tetwave-store`, as `tetwave-server prepare` runs them), [`stream`] (`tetwave-server
//! serve`: HTTP endpoints and the progressive WebSocket stream) and [`render_service`] (fallback
//! images and the viewer page).

pub mod analysis;
pub mod import;
pub mod prepare;
pub mod render_service;
pub mod resample;
pub mod stream;
