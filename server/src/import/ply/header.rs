//! The PLY header: magic, `format`, `element` and `property` lines up to `end_header`, one
//! helper per keyword. Counts are only recorded here; nothing is allocated from them.

use std::io::{BufRead, Read};

use super::super::{ImportError, show_bytes};

/// Longest accepted header line.
const MAX_LINE: u64 = 1 << 16;
/// Largest accepted header.
const MAX_HEADER: u64 = 1 << 20;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    pub(super) fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    pub(super) fn size(self) -> u64 {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    pub(super) fn is_int(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug, Clone)]
pub(super) struct Property {
    pub(super) name: String,
    pub(super) kind: Kind,
}

#[derive(Debug, Clone)]
pub(super) struct Element {
    pub(super) name: String,
    pub(super) count: u64,
    pub(super) props: Vec<Property>,
}

impl Element {
    pub(super) fn scalar(&self, name: &str) -> Option<(usize, Scalar)> {
        self.props
            .iter()
            .enumerate()
            .find_map(|(i, p)| match p.kind {
                Kind::Scalar(s) if p.name == name => Some((i, s)),
                _ => None,
            })
    }

    pub(super) fn list(&self, names: &[&str]) -> Option<usize> {
        self.props
            .iter()
            .position(|p| matches!(p.kind, Kind::List { .. }) && names.contains(&p.name.as_str()))
    }

    /// Smallest possible binary record size, and whether every record has exactly that size.
    pub(super) fn min_binary_size(&self) -> (u64, bool) {
        let mut size = 0u64;
        let mut fixed = true;
        for p in &self.props {
            match p.kind {
                Kind::Scalar(s) => size += s.size(),
                Kind::List { count, .. } => {
                    size += count.size();
                    fixed = false;
                }
            }
        }
        (size, fixed)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Encoding {
    Ascii,
    LittleEndian,
    BigEndian,
}

#[derive(Debug)]
pub(super) struct Header {
    pub(super) encoding: Encoding,
    pub(super) elements: Vec<Element>,
    /// Byte offset of the body.
    pub(super) data_start: u64,
    /// Number of header lines (ASCII body line numbers continue from here).
    pub(super) lines: u64,
}

pub(super) fn bad_header(file: &str, line: Option<u64>, detail: impl Into<String>) -> ImportError {
    ImportError::BadHeader {
        file: file.to_owned(),
        line,
        detail: detail.into(),
    }
}

/// Reads the header up to `end_header`.
pub(super) fn parse_header<R: BufRead>(r: &mut R, file: &str) -> Result<Header, ImportError> {
    let mut pos = read_magic(r, file)?;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut buf = Vec::new();
    let mut line_no = 1u64;
    loop {
        let (n, complete) = read_line(r, &mut buf)
            .map_err(|e| ImportError::io(file, "reading the PLY header", e))?;
        line_no += 1;
        let line = Some(line_no);
        if n == 0 {
            return Err(bad_header(file, line, "the file ends before 'end_header'"));
        }
        pos += n as u64;
        if !complete || pos > MAX_HEADER {
            return Err(bad_header(
                file,
                line,
                format!(
                    "header line too long or header larger than {MAX_HEADER} bytes without 'end_header'"
                ),
            ));
        }
        let text = String::from_utf8_lossy(&buf);
        let words: Vec<&str> = text.split_ascii_whitespace().collect();
        let Some(&keyword) = words.first() else {
            continue;
        };
        let at = HeaderLine {
            file,
            line,
            text: text.trim(),
            words: &words,
        };
        match keyword {
            "comment" | "obj_info" => {}
            "format" => encoding = Some(at.format()?),
            "element" => elements.push(at.element(&elements)?),
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(bad_header(file, line, "'property' before any 'element'"));
                };
                let property = at.property(element)?;
                element.props.push(property);
            }
            "end_header" => break,
            other => {
                return Err(bad_header(
                    file,
                    line,
                    format!("unknown header keyword '{other}'"),
                ));
            }
        }
    }
    let encoding = encoding.ok_or_else(|| bad_header(file, None, "missing 'format' line"))?;
    Ok(Header {
        encoding,
        elements,
        data_start: pos,
        lines: line_no,
    })
}

/// Reads `ply\n` (or `ply\r\n`); returns the bytes it took.
fn read_magic<R: BufRead>(r: &mut R, file: &str) -> Result<u64, ImportError> {
    let mut magic = [0u8; 4];
    let mut got = 0;
    while got < 4 {
        let n = r
            .read(&mut magic[got..])
            .map_err(|e| ImportError::io(file, "reading the PLY header", e))?;
        if n == 0 {
            break;
        }
        got += n;
    }
    let ok = match &magic[..got] {
        [b'p', b'l', b'y', b'\n'] => true,
        [b'p', b'l', b'y', b'\r'] => {
            // "ply\r\n": swallow the '\n'.
            let mut nl = [0u8; 1];
            r.read_exact(&mut nl).is_ok() && nl[0] == b'\n'
        }
        _ => false,
    };
    if !ok {
        return Err(ImportError::BadMagic {
            file: file.to_owned(),
            format: "PLY",
            expected: "ply\\n".to_owned(),
            found: show_bytes(&magic[..got]),
        });
    }
    Ok(if magic[3] == b'\r' { 5 } else { 4 })
}

/// Reads one line (up to `MAX_LINE` bytes) into `buf`; returns the bytes consumed (0 at EOF)
/// and whether the line is complete.
fn read_line<R: BufRead>(r: &mut R, buf: &mut Vec<u8>) -> std::io::Result<(usize, bool)> {
    buf.clear();
    let n = r.by_ref().take(MAX_LINE).read_until(b'\n', buf)?;
    let complete = buf.last() == Some(&b'\n') || n < MAX_LINE as usize;
    Ok((n, complete))
}

/// One header line, split into words, for the per-keyword parsers.
struct HeaderLine<'a> {
    file: &'a str,
    line: Option<u64>,
    text: &'a str,
    words: &'a [&'a str],
}

impl HeaderLine<'_> {
    fn bad(&self, detail: impl Into<String>) -> ImportError {
        bad_header(self.file, self.line, detail)
    }

    /// `format <ascii | binary_little_endian | binary_big_endian> 1.0`.
    fn format(&self) -> Result<Encoding, ImportError> {
        let words = self.words;
        if words.len() != 3 {
            return Err(self.bad(format!(
                "expected 'format <encoding> 1.0', got '{}'",
                self.text
            )));
        }
        let encoding = match words[1] {
            "ascii" => Encoding::Ascii,
            "binary_little_endian" => Encoding::LittleEndian,
            "binary_big_endian" => Encoding::BigEndian,
            other => {
                return Err(self.bad(format!(
                    "unknown format '{other}' (expected ascii, binary_little_endian or binary_big_endian)"
                )));
            }
        };
        if !matches!(words[2], "1.0" | "1") {
            return Err(self.bad(format!(
                "unsupported PLY version '{}' (expected 1.0)",
                words[2]
            )));
        }
        Ok(encoding)
    }

    /// `element <name> <count>`; names are unique.
    fn element(&self, elements: &[Element]) -> Result<Element, ImportError> {
        let [_, name, count] = self.words[..] else {
            return Err(self.bad(format!(
                "expected 'element <name> <count>', got '{}'",
                self.text
            )));
        };
        let count = match count.parse::<u64>() {
            Ok(c) => c,
            Err(_) if count.starts_with('-') && count[1..].parse::<u64>().is_ok() => {
                return Err(self.bad(format!("element '{name}' has negative count {count}")));
            }
            Err(_) => {
                return Err(self.bad(format!("element '{name}' has invalid count '{count}'")));
            }
        };
        if elements.iter().any(|e| e.name == name) {
            return Err(self.bad(format!("element '{name}' is declared twice")));
        }
        Ok(Element {
            name: name.to_owned(),
            count,
            props: Vec::new(),
        })
    }

    /// `property <type> <name>` or `property list <count type> <item type> <name>` of
    /// `element`; names are unique within the element.
    fn property(&self, element: &Element) -> Result<Property, ImportError> {
        let file = self.file;
        let ty = |what: String, name: &str| {
            Scalar::parse(name).ok_or_else(|| ImportError::UnsupportedType {
                file: file.to_owned(),
                what,
                type_name: name.to_owned(),
            })
        };
        let (name, kind) = match self.words[..] {
            [_, "list", count, item, name] => {
                let what = format!("property '{name}' of element '{}'", element.name);
                let count = ty(format!("list count of {what}"), count)?;
                let item = ty(what.clone(), item)?;
                if !count.is_int() {
                    return Err(ImportError::UnsupportedType {
                        file: file.to_owned(),
                        what: format!("list count of {what}"),
                        type_name: self.words[2].to_owned(),
                    });
                }
                (name, Kind::List { count, item })
            }
            [_, t, name] if t != "list" => {
                let what = format!("property '{name}' of element '{}'", element.name);
                (name, Kind::Scalar(ty(what, t)?))
            }
            _ => {
                return Err(self.bad(format!(
                    "expected 'property <type> <name>' or 'property list <count type> <item type> <name>', got '{}'",
                    self.text
                )));
            }
        };
        if element.props.iter().any(|p| p.name == name) {
            return Err(self.bad(format!(
                "property '{name}' of element '{}' is declared twice",
                element.name
            )));
        }
        Ok(Property {
            name: name.to_owned(),
            kind,
        })
    }
}
