//! VTK readers: XML `.vtu` (`UnstructuredGrid`) and legacy `.vtk` (`DATASET UNSTRUCTURED_GRID`).
//!
//! Both are written here rather than with `vtkio` (see the parent module for what `vtkio` 0.6.3
//! failed on). The XML is tokenized by `quick-xml`; zlib blocks are inflated by `flate2`; base64,
//! the block headers, the appended-data layout and the legacy grammar are ours.
//!
//! Files: `vtu.rs` reads a `.vtu` from the pieces and arrays that `xml.rs` collects from the XML
//! part of the file, decoding binary arrays with `binary.rs` (base64, block headers, zlib);
//! `legacy.rs` reads a legacy `.vtk`; `scalar.rs` has the VTK scalar types and their conversion,
//! which both formats use.

mod binary;
mod legacy;
mod scalar;
mod vtu;
mod xml;

pub(crate) use legacy::parse_legacy;
pub(crate) use vtu::parse_vtu;
