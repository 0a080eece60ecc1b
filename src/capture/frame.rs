//! The printed frame: a ring of tag36h11 tags around a square opening
//! (the sample shows through it), its layout in millimetres, and its
//! printable PDF (vector, so it prints at its true size) and PNG.
//!
//! Frame coordinates: millimetres on the paper, origin at the opening's
//! centre, x to the right and y up the page (the printed text is at the
//! bottom), z out of the paper. These are the capture folder's axes.
//!
//! Each opening size (whole centimetres) has its own block of tag ids, so
//! a photo's tags say which frame it shows: `flashmat capture` needs no
//! option to know the layout, and tags of two frames in one capture are
//! caught.

use anyhow::{anyhow, ensure, Result};

/// Side of a tag's black square, mm (the size a tag's pose is measured in).
pub const TAG_MM: f64 = 16.0;
/// Cells across a tag36h11 image: the 8-cell black square and a 1-cell
/// white ring on each side (`apriltag_to_image`).
pub const TAG_CELLS: usize = 10;
/// Cells across the black square.
const BLACK_CELLS: usize = 8;
/// White between the opening's edge and the tags' black squares, mm.
const OPENING_MARGIN_MM: f64 = 5.0;
/// Least white between two neighbouring black squares, mm.
const MIN_TAG_GAP_MM: f64 = 4.0;
/// Openings a frame can have, whole centimetres.
pub const OPENINGS_CM: std::ops::RangeInclusive<u32> = 5..=14;
/// Ids reserved per opening size (more than the largest ring holds).
const IDS_PER_FRAME: u32 = 48;
/// Length of the printed scale bar, mm.
pub const SCALE_BAR_MM: f64 = 100.0;

/// The paper a frame is printed on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Paper {
    A4,
    Letter,
}

impl Paper {
    /// Width and height, mm.
    pub fn size_mm(self) -> [f64; 2] {
        match self {
            Paper::A4 => [210.0, 297.0],
            Paper::Letter => [215.9, 279.4],
        }
    }
}

/// One tag of a frame: its id and the centre of its black square, mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TagPlace {
    pub id: u32,
    pub centre: [f64; 2],
}

/// A frame's layout: the opening and the ring of tags around it.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameLayout {
    pub opening_cm: u32,
    pub tags: Vec<TagPlace>,
}

impl FrameLayout {
    /// The frame with an opening of `opening_cm` centimetres: tags upright
    /// on a square ring, evenly spaced, corners included.
    pub fn new(opening_cm: u32) -> Result<Self> {
        ensure!(
            OPENINGS_CM.contains(&opening_cm),
            "--opening must be a whole number of centimetres from {} to {}, got {opening_cm}",
            OPENINGS_CM.start(),
            OPENINGS_CM.end()
        );
        let d = opening_cm as f64 * 5.0 + OPENING_MARGIN_MM + TAG_MM / 2.0;
        let per_side = ((2.0 * d) / (TAG_MM + MIN_TAG_GAP_MM)).floor() as usize + 1;
        let step = 2.0 * d / (per_side - 1) as f64;
        // Counter-clockwise from the bottom-left corner; each side leaves its
        // last tag to the next.
        let mut centres = Vec::new();
        for side in 0..4 {
            for k in 0..per_side - 1 {
                let s = -d + k as f64 * step;
                centres.push(match side {
                    0 => [s, -d],
                    1 => [d, s],
                    2 => [-s, d],
                    _ => [-d, -s],
                });
            }
        }
        let base = Self::id_base(opening_cm);
        let tags = centres.into_iter().enumerate().map(|(i, centre)| TagPlace { id: base + i as u32, centre }).collect::<Vec<_>>();
        debug_assert!(tags.len() as u32 <= IDS_PER_FRAME);
        Ok(Self { opening_cm, tags })
    }

    fn id_base(opening_cm: u32) -> u32 {
        (opening_cm - OPENINGS_CM.start()) * IDS_PER_FRAME
    }

    /// The opening of the frame a tag id belongs to, if any.
    pub fn opening_of(id: u32) -> Option<u32> {
        let cm = OPENINGS_CM.start() + id / IDS_PER_FRAME;
        let layout_len = Self::new(cm).ok()?.tags.len() as u32;
        (OPENINGS_CM.contains(&cm) && id % IDS_PER_FRAME < layout_len).then_some(cm)
    }

    /// Side of the opening, mm.
    pub fn opening_mm(&self) -> f64 {
        self.opening_cm as f64 * 10.0
    }

    /// Distance from the opening's centre to the middle of the white
    /// margin between the opening and the tags' black squares, mm: where
    /// the paper is read as a light meter (`capture::photometry`).
    pub fn paper_margin_centre_mm(&self) -> f64 {
        self.opening_mm() / 2.0 + OPENING_MARGIN_MM / 2.0
    }

    /// Half the side of the square the tags' white rings cover, mm.
    pub fn outer_half_mm(&self) -> f64 {
        let d = self.tags.iter().map(|t| t.centre[0].abs().max(t.centre[1].abs())).fold(0.0, f64::max);
        d + TAG_MM / 2.0 * TAG_CELLS as f64 / BLACK_CELLS as f64
    }

    pub fn find(&self, id: u32) -> Option<&TagPlace> {
        self.tags.iter().find(|t| t.id == id)
    }

    /// The corners of a tag's black square, mm, in the order the detector
    /// gives them ([`super::markers::Marker::corners`]): the detector's tag
    /// coordinates (-1, 1), (1, 1), (1, -1), (-1, -1), whose y runs down the
    /// tag's image, hence down the page.
    pub fn corners(tag: &TagPlace) -> [[f64; 2]; 4] {
        let h = TAG_MM / 2.0;
        let [x, y] = tag.centre;
        [[x - h, y - h], [x + h, y - h], [x + h, y + h], [x - h, y + h]]
    }
}

/// A tag36h11 tag as `TAG_CELLS x TAG_CELLS` cells, row-major from the
/// top, `true` where white: drawn by the AprilTag library itself.
pub fn tag_cells(id: u32) -> Result<Vec<bool>> {
    // SAFETY: the family and the image are created, read within their
    // bounds (the image's width, height and stride) and destroyed here; the
    // id is checked against the family's code count first.
    unsafe {
        let family = apriltag_sys::tag36h11_create();
        ensure!(!family.is_null(), "the AprilTag library could not create tag36h11");
        let ncodes = (*family).ncodes;
        if id >= ncodes {
            apriltag_sys::tag36h11_destroy(family);
            return Err(anyhow!("tag36h11 has {ncodes} tags, no id {id}"));
        }
        let image = apriltag_sys::apriltag_to_image(family, id as i32);
        let (w, h, stride) = ((*image).width as usize, (*image).height as usize, (*image).stride as usize);
        let cells = (0..h).flat_map(|r| (0..w).map(move |c| (r, c))).map(|(r, c)| *(*image).buf.add(r * stride + c) > 127).collect::<Vec<_>>();
        apriltag_sys::image_u8_destroy(image);
        apriltag_sys::tag36h11_destroy(family);
        ensure!(w == TAG_CELLS && h == TAG_CELLS, "tag36h11 images are {w}x{h} cells, expected {TAG_CELLS}");
        Ok(cells)
    }
}

/// Every black square of the frame (tag cells, merged along rows), as
/// `[x, y, width, height]` in frame mm with (x, y) the lower-left corner.
pub fn black_rects(layout: &FrameLayout) -> Result<Vec<[f64; 4]>> {
    let cell = TAG_MM / BLACK_CELLS as f64;
    let mut out = Vec::new();
    for tag in &layout.tags {
        let cells = tag_cells(tag.id)?;
        let left = tag.centre[0] - cell * TAG_CELLS as f64 / 2.0;
        let top = tag.centre[1] + cell * TAG_CELLS as f64 / 2.0;
        for r in 0..TAG_CELLS {
            let mut c = 0;
            while c < TAG_CELLS {
                if cells[r * TAG_CELLS + c] {
                    c += 1;
                    continue;
                }
                let start = c;
                while c < TAG_CELLS && !cells[r * TAG_CELLS + c] {
                    c += 1;
                }
                out.push([left + start as f64 * cell, top - (r + 1) as f64 * cell, (c - start) as f64 * cell, cell]);
            }
        }
    }
    Ok(out)
}

/// Where the frame sits on the page: the opening's centre, mm from the
/// page's lower-left corner. The frame is centred across and kept 15 mm
/// from the top; the text goes below.
pub fn frame_centre_on_page(layout: &FrameLayout, paper: Paper) -> Result<[f64; 2]> {
    let [w, h] = paper.size_mm();
    let outer = layout.outer_half_mm();
    ensure!(
        2.0 * outer + 20.0 <= w && 2.0 * outer + 75.0 <= h,
        "a {} cm opening's frame ({:.0} mm across) does not fit on {paper:?} paper",
        layout.opening_cm,
        2.0 * outer
    );
    Ok([w / 2.0, h - 15.0 - outer])
}

/// The lines printed under the frame: what it is and the scale check.
pub fn caption(layout: &FrameLayout) -> [String; 3] {
    [
        format!(
            "flashmat capture frame: tag36h11 ids {}-{}, opening {} cm, tags {} mm (black square).",
            layout.tags[0].id,
            layout.tags.last().map_or(0, |t| t.id),
            layout.opening_cm,
            TAG_MM
        ),
        format!("The bar above must measure {SCALE_BAR_MM} mm: print at 100% (no 'fit to page'). Cut out the square."),
        "Lay the frame flat on the material; take 3-5 flash photos, the flash's reflection inside the square.".to_string(),
    ]
}

/// The printed page in page millimetres (origin at its lower-left corner,
/// y up): what the PDF and the raster both draw.
pub struct Page {
    pub size_mm: [f64; 2],
    /// Black rectangles `[x, y, width, height]`.
    pub black: Vec<[f64; 4]>,
    /// The opening's cut line (a thin grey square), `[x, y, side, side]`.
    pub cut: [f64; 4],
    /// Thin black lines of the scale bar and its centimetre ticks.
    pub lines: Vec<([f64; 2], [f64; 2])>,
    /// The caption's lines and their baselines' heights.
    pub caption: Vec<(String, f64)>,
}

/// The page of a frame: the frame centred across, 15 mm from the top; under
/// it the scale bar ([`SCALE_BAR_MM`] with a tick each centimetre, longer
/// every 5) and the caption.
pub fn page(layout: &FrameLayout, paper: Paper) -> Result<Page> {
    let [cx, cy] = frame_centre_on_page(layout, paper)?;
    let black = black_rects(layout)?.into_iter().map(|[x, y, w, h]| [cx + x, cy + y, w, h]).collect();
    let half = layout.opening_mm() / 2.0;
    let bar_y = cy - layout.outer_half_mm() - 12.0;
    let bar_x = cx - SCALE_BAR_MM / 2.0;
    let mut lines = vec![([bar_x, bar_y], [bar_x + SCALE_BAR_MM, bar_y])];
    for k in 0..=(SCALE_BAR_MM / 10.0) as usize {
        let x = bar_x + k as f64 * 10.0;
        lines.push(([x, bar_y], [x, bar_y + if k % 5 == 0 { 4.0 } else { 2.0 }]));
    }
    let caption = caption(layout).into_iter().enumerate().map(|(i, line)| (line, bar_y - 10.0 - 6.0 * i as f64)).collect();
    Ok(Page { size_mm: paper.size_mm(), black, cut: [cx - half, cy - half, 2.0 * half, 2.0 * half], lines, caption })
}

/// 1 mm in PDF points.
const PT_PER_MM: f64 = 72.0 / 25.4;
/// The caption's left margin, mm.
const CAPTION_LEFT_MM: f64 = 15.0;

/// The frame as a one-page PDF: tags as filled rectangles, the opening's
/// cut line, the scale bar, and the caption (Helvetica).
pub fn frame_pdf(layout: &FrameLayout, paper: Paper) -> Result<Vec<u8>> {
    use pdf_writer::{Content, Name, Pdf, Rect, Ref, Str};
    let page = page(layout, paper)?;
    let p = |v: f64| (v * PT_PER_MM) as f32;
    let mut content = Content::new();
    content.set_fill_gray(0.0);
    for [x, y, w, h] in &page.black {
        content.rect(p(*x), p(*y), p(*w), p(*h));
    }
    content.fill_nonzero();
    let [x, y, w, h] = page.cut;
    content.set_stroke_gray(0.6).set_line_width(0.5).rect(p(x), p(y), p(w), p(h)).stroke();
    content.set_stroke_gray(0.0).set_line_width(0.8);
    for (a, b) in &page.lines {
        content.move_to(p(a[0]), p(a[1])).line_to(p(b[0]), p(b[1]));
    }
    content.stroke();
    let font = Name(b"F1");
    for (line, y) in &page.caption {
        content.begin_text().set_font(font, 9.0).next_line(p(CAPTION_LEFT_MM), p(*y)).show(Str(line.as_bytes())).end_text();
    }
    let (catalog, tree, page_id, font_id, content_id) = (Ref::new(1), Ref::new(2), Ref::new(3), Ref::new(4), Ref::new(5));
    let mut pdf = Pdf::new();
    pdf.catalog(catalog).pages(tree);
    pdf.pages(tree).kids([page_id]).count(1);
    let mut page_writer = pdf.page(page_id);
    page_writer.parent(tree).media_box(Rect::new(0.0, 0.0, p(page.size_mm[0]), p(page.size_mm[1]))).contents(content_id);
    page_writer.resources().fonts().pair(font, font_id);
    drop(page_writer);
    pdf.type1_font(font_id).base_font(Name(b"Helvetica"));
    pdf.stream(content_id, &content.finish());
    Ok(pdf.finish())
}

/// The frame as a grey image at `dpi` (a PNG to print at that resolution,
/// or to look at), `[1, H, W]` in [0, 1]: white paper, black tags, the grey
/// cut line, the scale bar. The caption is for the caller to draw
/// (`viz::annotate`): its lines with their left and baseline pixels.
pub fn frame_raster(layout: &FrameLayout, paper: Paper, dpi: f64) -> Result<(crate::image::Image, Vec<(String, [f64; 2])>)> {
    ensure!(dpi.is_finite() && (50.0..=1200.0).contains(&dpi), "--dpi must be from 50 to 1200, got {dpi}");
    let page = page(layout, paper)?;
    let [pw, ph] = page.size_mm;
    let px_per_mm = dpi / 25.4;
    let (w, h) = ((pw * px_per_mm).round() as usize, (ph * px_per_mm).round() as usize);
    let mut image = crate::image::Image::filled(1, h, w, 1.0);
    // Fills page mm [x0, x1] x [y0, y1] (rows run down the page).
    let mut fill = |x0: f64, y0: f64, x1: f64, y1: f64, value: f32| {
        let col = |x: f64| ((x * px_per_mm).round().max(0.0) as usize).min(w);
        let row = |y: f64| (((ph - y) * px_per_mm).round().max(0.0) as usize).min(h);
        for r in row(y1)..row(y0) {
            for c in col(x0)..col(x1) {
                image.set(0, r, c, value);
            }
        }
    };
    for [x, y, rw, rh] in &page.black {
        fill(*x, *y, x + rw, y + rh, 0.0);
    }
    let [x, y, side, _] = page.cut;
    let t = 0.2;
    for [x0, y0, x1, y1] in [[x, y, x + side, y + t], [x, y + side - t, x + side, y + side], [x, y, x + t, y + side], [x + side - t, y, x + side, y + side]] {
        fill(x0, y0, x1, y1, 0.6);
    }
    for (a, b) in &page.lines {
        let t = 0.15;
        fill(a[0].min(b[0]) - t, a[1].min(b[1]) - t, a[0].max(b[0]) + t, a[1].max(b[1]) + t, 0.0);
    }
    let caption = page.caption.into_iter().map(|(line, y)| (line, [CAPTION_LEFT_MM * px_per_mm, (ph - y) * px_per_mm])).collect();
    Ok((image, caption))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_fit_their_ids_and_paper() {
        for cm in OPENINGS_CM {
            let layout = FrameLayout::new(cm).unwrap();
            assert!(layout.tags.len() as u32 <= IDS_PER_FRAME, "{cm} cm: {} tags", layout.tags.len());
            for paper in [Paper::A4, Paper::Letter] {
                frame_centre_on_page(&layout, paper).unwrap();
            }
            for t in &layout.tags {
                assert_eq!(FrameLayout::opening_of(t.id), Some(cm));
            }
            // Neighbouring black squares keep their gap, and none covers the opening.
            for (i, a) in layout.tags.iter().enumerate() {
                assert!(a.centre[0].abs().max(a.centre[1].abs()) - TAG_MM / 2.0 >= layout.opening_mm() / 2.0 + OPENING_MARGIN_MM - 1e-9);
                for b in &layout.tags[i + 1..] {
                    let gap = (a.centre[0] - b.centre[0]).abs().max((a.centre[1] - b.centre[1]).abs()) - TAG_MM;
                    assert!(gap >= MIN_TAG_GAP_MM - 1e-9, "{cm} cm: tags {} and {} are {gap} mm apart", a.id, b.id);
                }
            }
        }
        // 10 cm: ring half-side 50 + 5 + 8 = 63 mm, floor(126 / 20) + 1 = 7 a side, 24 tags.
        let layout = FrameLayout::new(10).unwrap();
        assert_eq!(layout.tags.len(), 24);
        assert_eq!(layout.tags[0].centre, [-63.0, -63.0]);
        assert_eq!(FrameLayout::opening_of(IDS_PER_FRAME * 5 + 24), None);
        assert!(FrameLayout::new(15).is_err() && FrameLayout::new(4).is_err());
    }

    #[test]
    fn tags_have_a_white_ring_and_a_black_square() {
        let cells = tag_cells(0).unwrap();
        for i in 0..TAG_CELLS {
            for (r, c) in [(0, i), (TAG_CELLS - 1, i), (i, 0), (i, TAG_CELLS - 1)] {
                assert!(cells[r * TAG_CELLS + c], "the outer ring is white");
            }
        }
        for i in 1..TAG_CELLS - 1 {
            for (r, c) in [(1, i), (TAG_CELLS - 2, i), (i, 1), (i, TAG_CELLS - 2)] {
                assert!(!cells[r * TAG_CELLS + c], "the black square's border is black");
            }
        }
        assert_ne!(tag_cells(0).unwrap(), tag_cells(1).unwrap());
        assert!(tag_cells(587).is_err(), "tag36h11 has 587 codes");
    }

    #[test]
    fn the_pdf_is_a_true_size_page() {
        let layout = FrameLayout::new(10).unwrap();
        let pdf = frame_pdf(&layout, Paper::A4).unwrap();
        let text = String::from_utf8_lossy(&pdf);
        assert!(text.starts_with("%PDF-"));
        // A4 in points: 210 and 297 mm * 72 / 25.4.
        assert!(text.contains("/MediaBox [0 0 595.2756 841.8898]"), "{}", &text[..text.len().min(600)]);
        assert!(text.contains("/BaseFont /Helvetica"));
    }
}
