//! VTK scalar types (XML and legacy names) and their values from binary or ascii data.

use crate::lex::{show, Bad, Endian, Res};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    pub(super) fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    pub(super) fn from_xml(name: &str) -> Option<Scalar> {
        Some(match name {
            "Int8" | "Char" => Scalar::I8,
            "UInt8" => Scalar::U8,
            "Int16" => Scalar::I16,
            "UInt16" => Scalar::U16,
            "Int32" => Scalar::I32,
            "UInt32" => Scalar::U32,
            "Int64" => Scalar::I64,
            "UInt64" => Scalar::U64,
            "Float32" => Scalar::F32,
            "Float64" => Scalar::F64,
            _ => return None,
        })
    }
}

macro_rules! convert {
    ($bytes:expr, $endian:expr, $ty:ty, $map:expr) => {{
        const N: usize = std::mem::size_of::<$ty>();
        $bytes
            .chunks_exact(N)
            .map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                let v = match $endian {
                    Endian::Little => <$ty>::from_le_bytes(a),
                    Endian::Big => <$ty>::from_be_bytes(a),
                };
                $map(v)
            })
            .collect()
    }};
}

/// Binary values as f64 (`bytes.len()` a multiple of the scalar size; a tail is ignored).
pub(super) fn bytes_to_f64(bytes: &[u8], t: Scalar, e: Endian) -> Vec<f64> {
    match t {
        Scalar::I8 => bytes.iter().map(|&b| f64::from(b as i8)).collect(),
        Scalar::U8 => bytes.iter().map(|&b| f64::from(b)).collect(),
        Scalar::I16 => convert!(bytes, e, i16, f64::from),
        Scalar::U16 => convert!(bytes, e, u16, f64::from),
        Scalar::I32 => convert!(bytes, e, i32, f64::from),
        Scalar::U32 => convert!(bytes, e, u32, f64::from),
        Scalar::I64 => convert!(bytes, e, i64, |v: i64| v as f64),
        Scalar::U64 => convert!(bytes, e, u64, |v: u64| v as f64),
        Scalar::F32 => convert!(bytes, e, f32, f64::from),
        Scalar::F64 => convert!(bytes, e, f64, |v: f64| v),
    }
}

/// Binary values as i64; floating-point types and values past `i64::MAX` are refused.
pub(super) fn bytes_to_i64(bytes: &[u8], t: Scalar, e: Endian) -> Result<Vec<i64>, String> {
    Ok(match t {
        Scalar::I8 => bytes.iter().map(|&b| i64::from(b as i8)).collect(),
        Scalar::U8 => bytes.iter().map(|&b| i64::from(b)).collect(),
        Scalar::I16 => convert!(bytes, e, i16, i64::from),
        Scalar::U16 => convert!(bytes, e, u16, i64::from),
        Scalar::I32 => convert!(bytes, e, i32, i64::from),
        Scalar::U32 => convert!(bytes, e, u32, i64::from),
        Scalar::I64 => convert!(bytes, e, i64, |v: i64| v),
        Scalar::U64 => {
            let v: Vec<u64> = convert!(bytes, e, u64, |v: u64| v);
            v.into_iter()
                .map(i64::try_from)
                .collect::<Result<_, _>>()
                .map_err(|_| "holds a value past 2^63".to_string())?
        }
        Scalar::F32 | Scalar::F64 => {
            return Err(format!("has type {t:?}; expected an integer type"))
        }
    })
}

/// Parses whitespace-separated numbers.
pub(super) fn ascii_values<T: std::str::FromStr>(text: &[u8], what: &str) -> Res<Vec<T>> {
    let text = std::str::from_utf8(text)
        .map_err(|_| Bad::new(what, "ascii data is not valid UTF-8 text"))?;
    text.split_ascii_whitespace()
        .enumerate()
        .map(|(i, tok)| {
            tok.parse::<T>().map_err(|_| {
                Bad::new(
                    what,
                    format!("value {i} \"{}\" is not a number", show(tok.as_bytes())),
                )
            })
        })
        .collect()
}
