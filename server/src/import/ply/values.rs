//! Typed values of a PLY body: the binary readers (either byte order) and the ASCII tokenizer,
//! behind one [`Values`] trait so the element readers are written once.

use std::io::{BufRead, Read};

use super::header::Scalar;

/// Why reading one value failed.
pub(super) enum ReadErr {
    Eof,
    Io(std::io::Error),
    /// ASCII only: the token is not a number of the property's type.
    Syntax(String),
}

/// A source of typed values, binary or ASCII.
pub(super) trait Values {
    fn value(&mut self, ty: Scalar) -> Result<f64, ReadErr>;
    /// Skips `n` fixed-size values (binary) or tokens (ASCII).
    fn skip(&mut self, ty: Scalar, n: u64) -> Result<(), ReadErr> {
        for _ in 0..n {
            self.value(ty)?;
        }
        Ok(())
    }
    /// Current byte offset (binary) or line number (ASCII), for messages.
    fn position(&self) -> String;
    /// Current line (ASCII only).
    fn line(&self) -> Option<u64>;
}

pub(super) struct Binary<R> {
    pub(super) r: R,
    pub(super) pos: u64,
    pub(super) big: bool,
}

impl<R: BufRead> Values for Binary<R> {
    #[inline]
    fn value(&mut self, ty: Scalar) -> Result<f64, ReadErr> {
        let mut b = [0u8; 8];
        let n = ty.size() as usize;
        self.r.read_exact(&mut b[..n]).map_err(|e| match e.kind() {
            std::io::ErrorKind::UnexpectedEof => ReadErr::Eof,
            _ => ReadErr::Io(e),
        })?;
        self.pos += n as u64;
        if self.big {
            b[..n].reverse();
        }
        Ok(match ty {
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U8 => f64::from(b[0]),
            Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F64 => f64::from_le_bytes(b),
        })
    }

    fn skip(&mut self, ty: Scalar, n: u64) -> Result<(), ReadErr> {
        if n == 1 {
            return self.value(ty).map(|_| ());
        }
        let bytes = n.saturating_mul(ty.size());
        let copied = std::io::copy(&mut self.r.by_ref().take(bytes), &mut std::io::sink())
            .map_err(ReadErr::Io)?;
        self.pos += copied;
        if copied < bytes {
            return Err(ReadErr::Eof);
        }
        Ok(())
    }

    fn position(&self) -> String {
        format!("byte {}", self.pos)
    }

    fn line(&self) -> Option<u64> {
        None
    }
}

/// Longest accepted ASCII token (a number).
const MAX_TOKEN: usize = 256;

/// Whitespace-separated tokens straight from the buffered reader: no line-length limit, so a
/// whole triangle strip on one line is fine.
pub(super) struct Ascii<R> {
    r: R,
    tok: Vec<u8>,
    /// Line of the next unread byte (1-based, counting the header).
    line: u64,
}

impl<R: BufRead> Ascii<R> {
    /// Values from `r`, whose first line is line `line` of the file.
    pub(super) fn new(r: R, line: u64) -> Self {
        Self {
            r,
            tok: Vec::new(),
            line,
        }
    }

    fn token(&mut self) -> Result<&[u8], ReadErr> {
        self.tok.clear();
        // Skip whitespace, counting lines.
        loop {
            let buf = self.r.fill_buf().map_err(ReadErr::Io)?;
            if buf.is_empty() {
                return Err(ReadErr::Eof);
            }
            let mut i = 0;
            while i < buf.len() && buf[i].is_ascii_whitespace() {
                if buf[i] == b'\n' {
                    self.line += 1;
                }
                i += 1;
            }
            let exhausted = i == buf.len();
            self.r.consume(i);
            if !exhausted {
                break;
            }
        }
        // Collect the token.
        loop {
            let buf = self.r.fill_buf().map_err(ReadErr::Io)?;
            if buf.is_empty() {
                break;
            }
            let i = buf
                .iter()
                .position(|b| b.is_ascii_whitespace())
                .unwrap_or(buf.len());
            if self.tok.len() + i > MAX_TOKEN {
                return Err(ReadErr::Syntax(format!(
                    "value longer than {MAX_TOKEN} characters"
                )));
            }
            self.tok.extend_from_slice(&buf[..i]);
            let done = i < buf.len();
            self.r.consume(i);
            if done {
                break;
            }
        }
        Ok(&self.tok)
    }
}

impl<R: BufRead> Values for Ascii<R> {
    fn value(&mut self, ty: Scalar) -> Result<f64, ReadErr> {
        let tok = self.token()?;
        let s = std::str::from_utf8(tok).unwrap_or("");
        let parsed = if ty.is_int() {
            s.parse::<i64>().ok().map(|v| v as f64).or_else(|| {
                // Tolerate "3.0" for an integer property, nothing fractional.
                s.parse::<f64>().ok().filter(|v| v.fract() == 0.0)
            })
        } else {
            s.parse::<f64>().ok()
        };
        parsed.ok_or_else(|| {
            ReadErr::Syntax(format!(
                "'{}' is not a valid {}",
                String::from_utf8_lossy(tok),
                if ty.is_int() { "integer" } else { "number" }
            ))
        })
    }

    fn position(&self) -> String {
        format!("line {}", self.line)
    }

    fn line(&self) -> Option<u64> {
        Some(self.line)
    }
}
