//! Figures as files for test reports (`--figures svg|png|pdf`): the SVG that the pages
//! draw, written as it is, rasterised at 300 dpi (PNG, resvg), or converted to vector PDF
//! (svg2pdf). Text is laid out with DejaVu Sans, bundled in the binary: no system font is
//! looked for, so a figure reads the same on every machine. In: titled SVG figures; out:
//! one file per figure in a folder.

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use resvg::{tiny_skia, usvg};

use super::{write_atomic, ReportError};

/// The file format of written figures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FigureFormat {
    /// The SVG as drawn (vector, text as text).
    Svg,
    /// A raster image at [`PNG_DPI`].
    Png,
    /// A one-page vector PDF (text embedded with its font).
    Pdf,
}

impl FigureFormat {
    /// The file extension (and the format's name).
    pub fn extension(self) -> &'static str {
        match self {
            FigureFormat::Svg => "svg",
            FigureFormat::Png => "png",
            FigureFormat::Pdf => "pdf",
        }
    }
}

/// Resolution of PNG figures (dots per inch).
pub const PNG_DPI: f32 = 300.0;

/// CSS pixels per inch: the unit an SVG's size is given in.
const SVG_DPI: f32 = 96.0;

/// The family every figure's text is set in.
const FAMILY: &str = "DejaVu Sans";

/// The bundled fonts, loaded once per process.
fn fonts() -> Arc<usvg::fontdb::Database> {
    static DB: OnceLock<Arc<usvg::fontdb::Database>> = OnceLock::new();
    DB.get_or_init(|| {
        let mut db = usvg::fontdb::Database::new();
        db.load_font_data(dejavu::sans::regular().to_vec());
        db.load_font_data(dejavu::sans::bold().to_vec());
        db.set_sans_serif_family(FAMILY);
        db.set_serif_family(FAMILY);
        Arc::new(db)
    })
    .clone()
}

fn parse(svg: &str) -> Result<usvg::Tree, String> {
    let options = usvg::Options {
        font_family: FAMILY.into(),
        fontdb: fonts(),
        ..usvg::Options::default()
    };
    usvg::Tree::from_str(svg, &options).map_err(|e| format!("the figure's SVG: {e}"))
}

/// The figure in `format`, as the bytes of its file.
pub fn render(svg: &str, format: FigureFormat) -> Result<Vec<u8>, String> {
    match format {
        FigureFormat::Svg => Ok(svg.as_bytes().to_vec()),
        FigureFormat::Png => png(&parse(svg)?),
        FigureFormat::Pdf => svg2pdf::to_pdf(
            &parse(svg)?,
            svg2pdf::ConversionOptions::default(),
            svg2pdf::PageOptions { dpi: SVG_DPI },
        )
        .map_err(|e| format!("PDF conversion: {e}")),
    }
}

/// Rasterises at [`PNG_DPI`] and encodes with the resolution recorded (pHYs), so that a
/// word processor places the figure at its drawn size.
fn png(tree: &usvg::Tree) -> Result<Vec<u8>, String> {
    let scale = PNG_DPI / SVG_DPI;
    let size = tree
        .size()
        .to_int_size()
        .scale_by(scale)
        .ok_or("empty figure")?;
    let mut pixmap =
        tiny_skia::Pixmap::new(size.width(), size.height()).ok_or("figure too large")?;
    pixmap.fill(tiny_skia::Color::WHITE);
    resvg::render(
        tree,
        tiny_skia::Transform::from_scale(scale, scale),
        &mut pixmap.as_mut(),
    );
    // Opaque (drawn on white): RGB, without an alpha channel.
    let rgb: Vec<u8> = pixmap
        .pixels()
        .iter()
        .flat_map(|p| {
            let c = p.demultiply();
            [c.red(), c.green(), c.blue()]
        })
        .collect();
    let mut bytes = Vec::new();
    {
        let mut enc = ::png::Encoder::new(&mut bytes, size.width(), size.height());
        enc.set_color(::png::ColorType::Rgb);
        enc.set_depth(::png::BitDepth::Eight);
        // Plots are mostly flat colour: adaptive filtering makes the files about four
        // times smaller for a few milliseconds more (the best deflate level, 2× smaller
        // again, costs 80 ms a figure).
        enc.set_compression(::png::Compression::Default);
        enc.set_adaptive_filter(::png::AdaptiveFilterType::Adaptive);
        let per_metre = (PNG_DPI / 0.0254).round() as u32;
        enc.set_pixel_dims(Some(::png::PixelDimensions {
            xppu: per_metre,
            yppu: per_metre,
            unit: ::png::Unit::Meter,
        }));
        let mut w = enc.write_header().map_err(|e| e.to_string())?;
        w.write_image_data(&rgb).map_err(|e| e.to_string())?;
    }
    Ok(bytes)
}

/// Writes titled figures (title, SVG) into `dir` (created), each atomically as
/// `NN-title.EXT` ([`stem`]: numbered in order); returns the paths.
pub fn write_figures(
    dir: &Path,
    figures: &[(String, String)],
    format: FigureFormat,
) -> Result<Vec<PathBuf>, ReportError> {
    std::fs::create_dir_all(dir).map_err(|e| ReportError {
        file: dir.display().to_string(),
        detail: e.to_string(),
    })?;
    figures
        .iter()
        .enumerate()
        .map(|(i, (title, svg))| {
            let path = dir.join(format!("{}.{}", stem(i, title), format.extension()));
            let bytes = render(svg, format).map_err(|detail| ReportError {
                file: path.display().to_string(),
                detail,
            })?;
            write_atomic(&path, &bytes)?;
            Ok(path)
        })
        .collect()
}

/// A folder name for a run path: `/demo/effects/coulomb_friction` →
/// `demo-effects-coulomb_friction` (characters other than letters, digits, `_`, `.` and
/// `-` become `-`).
pub fn folder_name(run: &str) -> String {
    let s: String = run
        .trim_matches('/')
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '-') {
                c
            } else {
                '-'
            }
        })
        .collect();
    if s.is_empty() {
        "run".into()
    } else {
        s
    }
}

/// A file stem from a figure's number and title: `3`, "Backbone: skeleton" →
/// `03-backbone-skeleton`.
pub fn stem(index: usize, title: &str) -> String {
    let mut words = String::new();
    for c in title.chars() {
        if c.is_ascii_alphanumeric() {
            words.push(c.to_ascii_lowercase());
        } else if !words.ends_with('-') && !words.is_empty() {
            words.push('-');
        }
    }
    format!("{:02}-{}", index + 1, words.trim_end_matches('-'))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SVG: &str = r#"<svg xmlns="http://www.w3.org/2000/svg" width="200" height="100" viewBox="0 0 200 100"><rect width="200" height="100" fill="white"/><line x1="0" y1="50" x2="200" y2="50" stroke="black"/><text x="10" y="20" font-family="sans-serif" font-size="12">time (s)</text></svg>"#;

    #[test]
    fn png_is_300_dpi_with_its_resolution_recorded_and_text_drawn() {
        let bytes = render(SVG, FigureFormat::Png).unwrap();
        let decoder = ::png::Decoder::new(std::io::Cursor::new(&bytes));
        let mut reader = decoder.read_info().unwrap();
        let info = reader.info();
        // 200 × 100 CSS pixels at 300/96.
        assert_eq!((info.width, info.height), (625, 313));
        let dims = info.pixel_dims.unwrap();
        assert_eq!(dims.xppu, 11811);
        let mut buf = vec![0; reader.output_buffer_size()];
        reader.next_frame(&mut buf).unwrap();
        // The text's glyphs are drawn in the top-left corner (dark pixels above the line).
        let dark_above = buf
            .chunks(3)
            .enumerate()
            .filter(|(i, p)| (i / 625) < 140 && p[0] < 100)
            .count();
        assert!(
            dark_above > 50,
            "{dark_above} dark pixels where the text is"
        );
    }

    #[test]
    fn pdf_is_a_pdf_with_its_font_embedded() {
        let bytes = render(SVG, FigureFormat::Pdf).unwrap();
        assert!(bytes.starts_with(b"%PDF-"));
        let text = String::from_utf8_lossy(&bytes);
        assert!(text.contains("DejaVu"), "the font is embedded");
    }

    #[test]
    fn names_are_safe_file_names() {
        assert_eq!(
            folder_name("/demo/effects/coulomb_friction"),
            "demo-effects-coulomb_friction"
        );
        assert_eq!(folder_name("/"), "run");
        assert_eq!(
            stem(
                2,
                "Backbone: skeleton (circles) and fitted dead zone (line)"
            ),
            "03-backbone-skeleton-circles-and-fitted-dead-zone-line"
        );
        assert_eq!(stem(0, "A·ω0² (rad/s²)"), "01-a-0-rad-s");
    }
}
