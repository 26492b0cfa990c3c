//! Validates the WGSL passes at build time: each pass is `shaders/traverse.wgsl` followed by
//! the pass file; the concatenation is parsed and validated with naga, and a bad shader fails
//! `cargo build` with the file names and naga's message. The validated sources are written to
//! `OUT_DIR` for `arbor_client_gpu::shaders` to embed.

use std::path::{Path, PathBuf};

/// The passes: output name and the files concatenated, in order.
const PASSES: [(&str, [&str; 2]); 2] = [
    ("analysis.wgsl", ["traverse.wgsl", "analysis.wgsl"]),
    ("render.wgsl", ["traverse.wgsl", "render.wgsl"]),
];

fn main() {
    let manifest = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let shaders = manifest.join("../../shaders");
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("OUT_DIR"));
    for (name, files) in PASSES {
        let mut source = String::new();
        for f in files {
            let path = shaders.join(f);
            println!("cargo:rerun-if-changed={}", path.display());
            let text = std::fs::read_to_string(&path)
                .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
            source.push_str(&text);
            source.push('\n');
        }
        let label = files.join(" + ");
        if let Err(message) = validate(&source, &label) {
            eprintln!("{message}");
            panic!("shader {name} ({label}) is invalid:\n{message}");
        }
        write(&out.join(name), &source);
    }
}

fn validate(source: &str, label: &str) -> Result<(), String> {
    let module = naga::front::wgsl::parse_str(source)
        .map_err(|e| e.emit_to_string_with_path(source, label))?;
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .map_err(|e| e.emit_to_string_with_path(source, label))?;
    Ok(())
}

fn write(path: &Path, text: &str) {
    if std::fs::read_to_string(path).ok().as_deref() != Some(text) {
        std::fs::write(path, text).unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
    }
}
