//! SVG → PNG with `resvg`: usvg parses the SVG (its text set in the embedded DejaVu Sans), tiny-skia
//! rasterises it anti-aliased, one SVG pixel to one PNG pixel, on white.

use resvg::tiny_skia::{Color, Pixmap, Transform};
use resvg::usvg::{fontdb, Options, Tree};
use std::sync::{Arc, OnceLock};

/// The font database: DejaVu Sans (regular and bold) only, answering for `sans-serif`.
fn fonts() -> Arc<fontdb::Database> {
    static DB: OnceLock<Arc<fontdb::Database>> = OnceLock::new();
    DB.get_or_init(|| {
        let mut db = fontdb::Database::new();
        db.load_font_data(dejavu::sans::regular().to_vec());
        db.load_font_data(dejavu::sans::bold().to_vec());
        db.set_sans_serif_family("DejaVu Sans");
        Arc::new(db)
    })
    .clone()
}

/// The PNG bytes of the SVG text `svg`.
pub fn png(svg: &str) -> crate::Result<Vec<u8>> {
    let options = Options {
        font_family: "DejaVu Sans".into(),
        fontdb: fonts(),
        ..Options::default()
    };
    let tree =
        Tree::from_str(svg, &options).map_err(|e| crate::Error::Usage(format!("SVG: {e}")))?;
    let size = tree.size().to_int_size();
    let mut pixmap = Pixmap::new(size.width(), size.height()).ok_or_else(|| {
        crate::Error::Usage(format!("empty figure ({}×{})", size.width(), size.height()))
    })?;
    pixmap.fill(Color::WHITE);
    resvg::render(&tree, Transform::identity(), &mut pixmap.as_mut());
    pixmap
        .encode_png()
        .map_err(|e| crate::Error::Usage(format!("PNG: {e}")))
}
