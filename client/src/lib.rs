//! # tetwave-client
//!
//! The client side of tetwave. Stages land one module at a time (detail buffer, adaptive mesh,
//! selection, renderer, stream); for now [`store_info`] checks a store's base mesh and counts against
//! the protocol contract, from the client's side.

pub mod store_info;
