//! Small helpers over `hdf5-metno` shared by ingestion and the archive writers.
//!
//! libhdf5 is not thread-safe as Debian builds it; `hdf5-metno` serialises every call
//! through one process-wide reentrant lock, so these helpers may be called from any thread
//! (concurrent HDF5 work simply queues on that lock).

use hdf5::types::{FixedAscii, FixedUnicode, TypeDescriptor, VarLenAscii, VarLenUnicode};
use hdf5::{Attribute, Location};

/// A scalar attribute value as read from a file, numbers and strings only.
#[derive(Debug, Clone, PartialEq)]
pub enum AttrValue {
    /// Any integer or float attribute, converted to f64 (first element of a small array).
    Number(f64),
    /// Any string attribute (variable- or fixed-length, ASCII or UTF-8).
    Text(String),
    /// Something else (compound, array of many numbers, references): shown, not used.
    Other(String),
}

impl std::fmt::Display for AttrValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AttrValue::Number(x) => write!(f, "{x}"),
            AttrValue::Text(s) => write!(f, "{s}"),
            AttrValue::Other(s) => write!(f, "<{s}>"),
        }
    }
}

/// Reads one attribute as a number or a string; `Err` carries a human-readable reason.
pub fn read_attr(attr: &Attribute) -> Result<AttrValue, String> {
    let desc = attr
        .dtype()
        .and_then(|d| d.to_descriptor())
        .map_err(|e| e.to_string())?;
    let n = attr.size();
    match desc {
        TypeDescriptor::Float(_) | TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => {
            if n == 0 {
                return Err("empty numeric attribute".into());
            }
            let v: Vec<f64> = attr.read_raw::<f64>().map_err(|e| e.to_string())?;
            if v.len() == 1 {
                Ok(AttrValue::Number(v[0]))
            } else {
                Ok(AttrValue::Other(format!("{} numbers", v.len())))
            }
        }
        TypeDescriptor::VarLenUnicode => {
            first_string(attr.read_raw::<VarLenUnicode>(), |s| s.as_str().to_string())
        }
        TypeDescriptor::VarLenAscii => {
            first_string(attr.read_raw::<VarLenAscii>(), |s| s.as_str().to_string())
        }
        TypeDescriptor::FixedAscii(len) if len <= 4096 => {
            first_string(attr.read_raw::<FixedAscii<4096>>(), |s| {
                s.as_str().trim_end_matches('\0').to_string()
            })
        }
        TypeDescriptor::FixedUnicode(len) if len <= 4096 => {
            first_string(attr.read_raw::<FixedUnicode<4096>>(), |s| {
                s.as_str().trim_end_matches('\0').to_string()
            })
        }
        other => Ok(AttrValue::Other(format!("{other}"))),
    }
}

fn first_string<T>(r: hdf5::Result<Vec<T>>, f: impl Fn(&T) -> String) -> Result<AttrValue, String> {
    let v = r.map_err(|e| e.to_string())?;
    match v.first() {
        Some(s) => Ok(AttrValue::Text(f(s))),
        None => Err("empty string attribute".into()),
    }
}

/// All attributes of a location, in name order; unreadable ones are reported as `Other`.
pub fn all_attrs(loc: &Location) -> Vec<(String, AttrValue)> {
    let mut names = loc.attr_names().unwrap_or_default();
    names.sort();
    names
        .into_iter()
        .map(|name| {
            let value = match loc.attr(&name) {
                Ok(a) => read_attr(&a).unwrap_or_else(AttrValue::Other),
                Err(e) => AttrValue::Other(e.to_string()),
            };
            (name, value)
        })
        .collect()
}

/// Writes (or replaces) a UTF-8 string attribute.
pub fn write_str_attr(loc: &Location, name: &str, value: &str) -> hdf5::Result<()> {
    if loc.attr_names()?.iter().any(|n| n == name) {
        loc.delete_attr(name)?;
    }
    new_str_attr(loc, name, value)
}

/// Creates a UTF-8 string attribute that `loc` does not have yet. Cheaper than
/// [`write_str_attr`], which lists every attribute first: on a group of 50 attributes
/// written one by one that listing was most of the results writer's time.
pub fn new_str_attr(loc: &Location, name: &str, value: &str) -> hdf5::Result<()> {
    let v: VarLenUnicode = value
        .parse()
        .map_err(|e| hdf5::Error::from(format!("string attribute {name}: {e}")))?;
    loc.new_attr::<VarLenUnicode>()
        .create(name)?
        .write_scalar(&v)
}

/// Writes (or replaces) a float attribute.
pub fn write_f64_attr(loc: &Location, name: &str, value: f64) -> hdf5::Result<()> {
    if loc.attr_names()?.iter().any(|n| n == name) {
        loc.delete_attr(name)?;
    }
    new_f64_attr(loc, name, value)
}

/// Creates a float attribute that `loc` does not have yet (see [`new_str_attr`]).
pub fn new_f64_attr(loc: &Location, name: &str, value: f64) -> hdf5::Result<()> {
    loc.new_attr::<f64>().create(name)?.write_scalar(&value)
}
