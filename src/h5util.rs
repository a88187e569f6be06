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

/// String attributes read as an array at most this long (the first is used).
const MAX_STRINGS: usize = 1024;

/// Reads one attribute as a number or a string; `Err` carries a human-readable reason.
pub fn read_attr(attr: &Attribute) -> Result<AttrValue, String> {
    let desc = attr
        .dtype()
        .and_then(|d| d.to_descriptor())
        .map_err(|e| e.to_string())?;
    let n = attr.size();
    // Only what is used is read: a corrupt dataspace can claim 10^18 elements, and reading
    // them all would abort the process on the allocation.
    match desc {
        TypeDescriptor::Float(_) | TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => {
            match n {
                0 => Err("empty numeric attribute".into()),
                1 => {
                    let v: Vec<f64> = attr.read_raw::<f64>().map_err(|e| e.to_string())?;
                    v.first()
                        .map(|&x| AttrValue::Number(x))
                        .ok_or_else(|| "empty numeric attribute".into())
                }
                n => Ok(AttrValue::Other(format!("{n} numbers"))),
            }
        }
        _ if n > MAX_STRINGS => Ok(AttrValue::Other(format!("{n} values"))),
        // The bytes, never the crate's `as_str`: it trusts them to be UTF-8 unchecked, and a
        // test bench's Latin-1 unit ("\xb5m") or a corrupt string made an invalid `String`
        // (undefined behaviour; a debug build aborted on it in `Quantity::parse`).
        TypeDescriptor::VarLenUnicode => {
            first_string(attr.read_raw::<VarLenUnicode>(), |s| text(s.as_bytes()))
        }
        TypeDescriptor::VarLenAscii => {
            first_string(attr.read_raw::<VarLenAscii>(), |s| text(s.as_bytes()))
        }
        TypeDescriptor::FixedAscii(len) if len <= 4096 => {
            first_string(attr.read_raw::<FixedAscii<4096>>(), |s| text(s.as_bytes()))
        }
        TypeDescriptor::FixedUnicode(len) if len <= 4096 => {
            first_string(attr.read_raw::<FixedUnicode<4096>>(), |s| {
                text(s.as_bytes())
            })
        }
        other => Ok(AttrValue::Other(format!("{other}"))),
    }
}

/// A string attribute's bytes as text: invalid UTF-8 replaced (U+FFFD), padding dropped.
fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes)
        .trim_end_matches('\0')
        .to_string()
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

/// Creates many new scalar attributes (UTF-8 strings and floats) with one datatype, one
/// scalar dataspace and one creation list made once, as [`new_str_attr`] and
/// [`new_f64_attr`] would make them for every call: the results writer creates about 150
/// attributes per run, and making those three per attribute (and the binding's checks of
/// each handle) was half of what its attributes cost.
pub struct AttrMaker {
    text: hdf5::Datatype,
    number: hdf5::Datatype,
    scalar: hdf5::Dataspace,
    acpl: hdf5::plist::AttributeCreate,
}

impl AttrMaker {
    /// Makes the shared type, space and creation list (the same the binding makes).
    pub fn new() -> hdf5::Result<AttrMaker> {
        Ok(AttrMaker {
            text: hdf5::Datatype::from_type::<VarLenUnicode>()?,
            number: hdf5::Datatype::from_type::<f64>()?,
            scalar: hdf5::Dataspace::try_new(())?,
            acpl: hdf5::plist::AttributeCreate::build()
                .char_encoding(hdf5::plist::CharEncoding::Utf8)
                .finish()?,
        })
    }

    /// Creates the string attribute `name` (which `loc` must not have) holding `value`.
    pub fn text(&self, loc: &Location, name: &str, value: &str) -> hdf5::Result<()> {
        let c = std::ffi::CString::new(value)
            .map_err(|e| hdf5::Error::from(format!("string attribute {name}: {e}")))?;
        // A variable-length string's memory form is a pointer to its bytes.
        let ptr = c.as_ptr();
        self.create(
            loc,
            name,
            &self.text,
            (&ptr as *const *const std::ffi::c_char).cast(),
        )
    }

    /// Creates the float attribute `name` (which `loc` must not have) holding `value`.
    pub fn number(&self, loc: &Location, name: &str, value: f64) -> hdf5::Result<()> {
        self.create(loc, name, &self.number, (&value as *const f64).cast())
    }

    fn create(
        &self,
        loc: &Location,
        name: &str,
        dtype: &hdf5::Datatype,
        buf: *const std::ffi::c_void,
    ) -> hdf5::Result<()> {
        use hdf5_sys::h5a::{H5Aclose, H5Acreate2, H5Awrite};
        let cname = std::ffi::CString::new(name)
            .map_err(|e| hdf5::Error::from(format!("attribute name {name:?}: {e}")))?;
        // The binding serialises every libhdf5 call behind one lock; raw calls take it too.
        let status = hdf5::sync::sync(|| unsafe {
            let id = H5Acreate2(
                loc.id(),
                cname.as_ptr(),
                dtype.id(),
                self.scalar.id(),
                self.acpl.id(),
                hdf5_sys::h5p::H5P_DEFAULT,
            );
            if id < 0 {
                return -1;
            }
            let written = H5Awrite(id, dtype.id(), buf);
            let closed = H5Aclose(id);
            if written < 0 {
                written
            } else {
                closed
            }
        });
        if status < 0 {
            Err(hdf5::Error::from(format!(
                "cannot create attribute {name} on {}",
                loc.name()
            )))
        } else {
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// String attributes that are not UTF-8 (a test bench's Latin-1 "µm" and "°C", or a
    /// corrupt string) read as text with U+FFFD where a byte is not UTF-8, never as an
    /// invalid `String`; valid ones read unchanged.
    #[test]
    fn strings_that_are_not_utf8_read_with_replacement_characters() {
        let dir = tempfile::tempdir().unwrap();
        let f = hdf5::File::create(dir.path().join("latin1.h5")).unwrap();
        // SAFETY: the bytes are only written to the file, never viewed as `str` here.
        let (micro, degree) = unsafe {
            (
                VarLenAscii::from_ascii_unchecked(b"\xb5m"),
                FixedAscii::<8>::from_ascii_unchecked(b"50 \xb0C"),
            )
        };
        f.new_attr::<VarLenAscii>()
            .create("units")
            .unwrap()
            .write_scalar(&micro)
            .unwrap();
        f.new_attr::<FixedAscii<8>>()
            .create("temperature")
            .unwrap()
            .write_scalar(&degree)
            .unwrap();
        let fine: VarLenUnicode = "µm".parse().unwrap();
        f.new_attr::<VarLenUnicode>()
            .create("utf8")
            .unwrap()
            .write_scalar(&fine)
            .unwrap();
        let attrs = all_attrs(&f);
        println!("{attrs:?}");
        let text = |name: &str| match &attrs.iter().find(|(n, _)| n == name).unwrap().1 {
            AttrValue::Text(s) => s.clone(),
            other => panic!("{name}: {other:?}"),
        };
        assert_eq!(text("units"), "\u{fffd}m");
        assert_eq!(text("temperature"), "50 \u{fffd}C");
        assert_eq!(text("utf8"), "µm");
    }
}
