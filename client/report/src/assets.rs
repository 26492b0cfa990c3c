//! Files compiled into the client: the one font, shared by the report charts and the viewer's
//! overlay so it is embedded once.

/// DejaVu Sans (Bitstream Vera licence, see `client/assets/README.md`).
pub static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");
