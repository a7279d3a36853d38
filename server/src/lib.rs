//! # tetwave-server
//!
//! The server side of tetwave, one module per pipeline stage:
//! [`import`] (reading the user's mesh files), [`resample`] (volume → semi-regular mesh samples),
//! [`analysis`] (lifting → detail nodes), [`store`] (coefficients on disk, random access by node id)
//! and [`prepare`] (the three in a row, as `tetwave-server prepare` runs them), [`stream`]
//! (`tetwave-server serve`: HTTP endpoints and the progressive WebSocket stream) and
//! [`render_service`] (fallback images and the viewer page).

pub mod analysis;
pub mod import;
pub mod prepare;
pub mod render_service;
pub mod resample;
pub mod store;
pub mod stream;
