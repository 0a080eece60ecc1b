use super::synthetic::{as_phone_photo, opening_truth, phone_views, render_photo, PhoneEffects, PhoneView};
use super::*;
use crate::geometry::sub;

/// A phone at 26 mm equivalent on a 1200 x 900 sensor: f = 26 / 43.27 * 1500 px.
const FOCAL: f64 = 901.3;
const W: usize = 1200;
const H: usize = 900;

/// The overhead photo and three tilted ones whose reflections (straight
/// below each phone) land inside the opening (mm, 10 cm frame).
const EYES: [Vec3; 4] = [[0.0, 0.0, 260.0], [42.0, -33.0, 250.0], [-38.0, 43.0, 255.0], [40.0, 38.0, 243.0]];

fn material() -> crate::svbrdf::Svbrdf {
    crate::data::procedural::test_material(3, 96)
}

/// Synthetic photos of the 10 cm frame from `views`, the flash `offset` mm
/// beside each lens (camera frame), with the truth of each opening.
fn shoot(views: &[PhoneView], offset: [f64; 2], fx: PhoneEffects, dir: &Path) -> (Vec<FramePhoto>, Vec<crate::image::Image>) {
    let layout = FrameLayout::new(10).unwrap();
    let shots = super::synthetic::shoot(&material(), &layout, views, offset, super::synthetic::SUPERSAMPLE, &fx).unwrap();
    shots
        .into_iter()
        .enumerate()
        .map(|(i, s)| (FramePhoto { path: dir.join(format!("IMG_{i}.jpg")), rgb: s.rgb, exif_focal: Some(FOCAL), orientation: 1, exposure: None, raw: None }, s.truth))
        .unzip()
}

fn views(k1: f64) -> Vec<PhoneView> {
    phone_views(&EYES, &[0.0, 12.0, -20.0, 35.0], W, H, FOCAL, k1, 0.0)
}

#[test]
fn detected_corners_land_on_the_projected_frame() {
    // Straight overhead, no distortion, no blur or noise: the detector's
    // corners on the true projection (both put pixel centres at +0.5).
    let v = phone_views(&[[0.0, 0.0, 260.0]], &[0.0], W, H, FOCAL, 0.0, 0.0);
    let fx = PhoneEffects { blur_px: 0.0, noise: 0.0, jpeg_quality: None, seed: 0 };
    let (photos, _) = shoot(&v, [0.0, 0.0], fx, Path::new("."));
    let (layout, found) = find_frame(&photos[0], 2).unwrap();
    assert_eq!(layout.opening_cm, 10);
    assert_eq!(found.len(), layout.tags.len(), "every tag is seen");
    let (mut worst, mut mean): (f64, f64) = (0.0, 0.0);
    for m in &found {
        let tag = layout.find(m.id).unwrap();
        for (w, px) in FrameLayout::corners(tag).iter().zip(&m.corners) {
            let truth = v[0].pose.project(&v[0].intrinsics, [w[0], w[1], 0.0]).unwrap();
            worst = worst.max((truth[0] - px[0]).hypot(truth[1] - px[1]));
            mean += (truth[0] - px[0]).hypot(truth[1] - px[1]) / (4 * found.len()) as f64;
        }
    }
    // The detector's corners scatter by a few tenths of a pixel (its edge
    // fits); no offset is left (a pixel-centre mix-up would make it 0.7).
    assert!(mean < 0.3 && worst < 0.8, "corners are {mean:.3} px off their projection on average, {worst:.3} at worst");
}

#[test]
fn a_phone_capture_comes_back_within_2_mm_half_a_degree_and_a_pixel() {
    let dir = tempfile::tempdir().unwrap();
    let views = views(-0.06);
    let (photos, truths) = shoot(&views, [8.0, -3.0], PhoneEffects::default(), dir.path());
    let cfg = CaptureConfig { flash_offset_mm: [8.0, -3.0], ..Default::default() };
    let cap = capture(&photos, &cfg, |_, _, _| {}).unwrap();
    assert_eq!(cap.photos[0].source, photos[0].path, "the overhead photo comes first");
    let half = cap.layout.opening_mm() / 2.0;
    for (result, view) in cap.photos.iter().zip(&views) {
        let truth = view.pose.centre();
        let d = length(sub(result.camera, truth));
        let angle = camera::rotation_angle_deg(&result.pose.rotation, &view.pose.rotation);
        assert!(d < 2.0, "{}: camera {d:.2} mm off", result.source.display());
        assert!(angle < 0.5, "{}: {angle:.3} degrees off", result.source.display());
        let light = add(truth, view.pose.to_world_dir([8.0, -3.0, 0.0]));
        assert!(length(sub(result.light, light)) < 2.0);
        // Each rectified pixel's centre, followed through the fitted camera
        // back onto the true plane, lands within a pixel of where it belongs.
        let mut worst: f64 = 0.0;
        for i in 0..=10 {
            for j in 0..=10 {
                let w = [-half + 2.0 * half * i as f64 / 10.0, -half + 2.0 * half * j as f64 / 10.0];
                let px = result.pose.project(&result.intrinsics, [w[0], w[1], 0.0]).unwrap();
                let back = view.pose.plane_point(&view.intrinsics, px).unwrap();
                worst = worst.max((back[0] - w[0]).hypot(back[1] - w[1]) * cap.side as f64 / (2.0 * half));
            }
        }
        assert!(worst < 1.0, "{}: the rectified sample is {worst:.2} px off", result.source.display());
    }
    assert!(cap.distortion, "k1 = -0.06 is fitted");
    // The rectified openings match the truth they were rendered from.
    for (n, rect) in cap.rectified.iter().enumerate() {
        let truth = truths[n].resize_bilinear(cap.side, cap.side);
        let err = rect.iter().zip(&truth.data).map(|(a, b)| (a - b).abs() as f64).sum::<f64>() / rect.len() as f64;
        let level = truth.data.iter().map(|&v| v as f64).sum::<f64>() / rect.len() as f64;
        assert!(err < 0.12 * level, "photo {n}: mean error {err:.4} on a level of {level:.4}");
    }

    // What an interrupted run left (its process ended): removed by the next.
    let mut child = std::process::Command::new("true").spawn().unwrap();
    let dead = child.id();
    child.wait().unwrap();
    let leftover = dir.path().join(format!(".capture.tmp-{dead}-0"));
    std::fs::create_dir(&leftover).unwrap();
    std::fs::write(leftover.join("00.png"), b"partial").unwrap();
    let out = dir.path().join("capture");
    write_folder(&cap, &out, &photos).unwrap();
    assert!(!leftover.exists(), "the interrupted run's folder is left");
    let folder = crate::data::captures::Captures::open(&out).unwrap();
    assert_eq!(folder.photos.len(), 4);
    assert_eq!(folder.sample_width, 100.0);
    // Positions in flashmat units: mm / 50.
    let c = cap.photos[1].camera;
    assert!((folder.cameras[1][0] - c[0] / 50.0).abs() < 1e-3 && (folder.cameras[1][2] - c[2] / 50.0).abs() < 1e-3);
    assert!(out.join("capture.jpg").is_file());
    assert_eq!(folder.exposures, [[1.0; 3]; 4]);
    assert!(!out.join(crate::data::captures::EXPOSURES_FILE).exists(), "one exposure: no exposures.txt");
    // The frame's paper reads one exposure in every photo.
    let levels = photometry::relative_levels(&cap.paper).expect("every photo's paper is read");
    assert!(!photometry::levels_differ(&levels), "{levels:?}");
    // Photo 2's EXIF says a stop darker but its pixels are the others':
    // the paper's reading wins, and the folder has one exposure.
    let mut bracketed: Vec<FramePhoto> = photos.iter().map(FramePhoto::clone_photo).collect();
    for (i, p) in bracketed.iter_mut().enumerate() {
        p.exposure = Some(crate::infer::camera::Exposure { time_s: Some(if i == 2 { 1.0 / 120.0 } else { 1.0 / 60.0 }), f_number: Some(1.8), iso: Some(100) });
    }
    let out = dir.path().join("bracketed");
    write_folder(&cap, &out, &bracketed).unwrap();
    assert!(!out.join(crate::data::captures::EXPOSURES_FILE).exists());
    // Photo 2 really darker, with another white balance (auto exposure and
    // auto white balance): the paper measures it, the folder records it.
    let gains = [0.5, 0.42, 0.6];
    bracketed[2].rgb.data.iter_mut().enumerate().for_each(|(i, code)| {
        *code = crate::spaces::quantize_u8(crate::spaces::photo_encode(crate::spaces::photo_decode(*code as f32 / 255.0) * gains[i % 3]));
    });
    let cap = capture(&bracketed, &cfg, |_, _, _| {}).unwrap();
    let out = dir.path().join("auto-exposed");
    write_folder(&cap, &out, &bracketed).unwrap();
    let folder = crate::data::captures::Captures::open(&out).unwrap();
    for (result, e) in cap.photos.iter().zip(&folder.exposures) {
        let want = if result.source == photos[2].path { gains } else { [1.0; 3] };
        for c in 0..3 {
            assert!((e[c] / want[c] as f64 - 1.0).abs() < 0.02, "{}: exposure {e:?}, want {want:?}", result.source.display());
        }
    }
}

#[test]
fn bad_photos_are_named_and_leave_no_folder() {
    let dir = tempfile::tempdir().unwrap();
    let views = views(0.0);
    let fx = PhoneEffects { jpeg_quality: None, ..Default::default() };
    let (mut photos, _) = shoot(&views[..3], [0.0, 0.0], fx, dir.path());
    let cfg = CaptureConfig::default();
    let out = dir.path().join("capture");
    let err = |photos: &[FramePhoto]| format!("{:#}", capture(photos, &cfg, |_, _, _| {}).err().expect("an error"));

    // Fewer than two photos.
    assert!(err(&photos[..1]).contains("at least 2 photos"));

    // Most of the frame covered: too few tags.
    let mut covered = FramePhoto { path: dir.path().join("covered.jpg"), rgb: Rgb8 { width: W, height: H, data: photos[1].rgb.data.clone() }, exif_focal: Some(FOCAL), orientation: 1, exposure: None, raw: None };
    for y in 0..H {
        for x in (W / 3)..W {
            covered.rgb.data[3 * (y * W + x)..3 * (y * W + x) + 3].fill(128);
        }
    }
    let e = err(&[photos[0].clone_photo(), covered]);
    assert!(e.starts_with("covered.jpg: only ") && e.contains("at least 4"), "{e}");

    // Blurred beyond detection.
    let blurred_view = PhoneEffects { blur_px: 7.0, jpeg_quality: None, ..Default::default() };
    let (blurred, _) = shoot(&views[1..2], [0.0, 0.0], blurred_view, &dir.path().join("b"));
    let e = err(&[photos[0].clone_photo(), blurred.into_iter().next().unwrap()]);
    assert!(e.contains("IMG_0.jpg: no frame tags found") && e.contains("blurred"), "{e}");

    // A white (over-exposed) or black (covered lens) photo: said so, not "blurred".
    for (level, what) in [(255u8, "white"), (3, "black")] {
        let flat = FramePhoto { path: dir.path().join("flat.jpg"), rgb: Rgb8 { width: W, height: H, data: vec![level; 3 * W * H] }, exif_focal: Some(FOCAL), orientation: 1, exposure: None, raw: None };
        let e = err(&[photos[0].clone_photo(), flat]);
        assert!(e.starts_with("flat.jpg: the photo is one level everywhere") && e.contains(what), "{e}");
    }

    // Tags of a layout they do not belong to: the 10 cm frame's tags
    // moved 4 mm outward (a frame scaled unevenly, or another layout).
    let mut moved = photos[2].clone_photo();
    moved.path = dir.path().join("moved.jpg");
    let layout = FrameLayout::new(10).unwrap();
    let stretched = FrameLayout { tags: layout.tags.iter().map(|t| frame::TagPlace { id: t.id, centre: t.centre.map(|c| c * 1.07) }).collect(), ..layout.clone() };
    let m = material();
    let truth = opening_truth(&m, &layout, views[2].pose.centre(), views[2].pose.centre(), 260.0).unwrap();
    let linear = render_photo(&stretched, &truth, views[2].pose.centre(), 260.0, &views[2], super::synthetic::SUPERSAMPLE).unwrap();
    moved.rgb = as_phone_photo(&linear, &fx).unwrap();
    let e = err(&[photos[0].clone_photo(), photos[1].clone_photo(), moved]);
    assert!(e.contains("off the frame's layout") || e.contains("focal length"), "{e}");

    // A grey card over the opening's left half in photo 1 (the box around
    // that half's corners as the photo sees them): named, with its share.
    let half = layout.opening_mm() / 2.0;
    let corners: Vec<[f64; 2]> = [[-half, -half], [0.0, -half], [0.0, half], [-half, half]].iter().map(|&[x, y]| views[1].pose.project(&views[1].intrinsics, [x, y, 0.0]).unwrap()).collect();
    let (x0, x1) = (corners.iter().map(|c| c[0]).fold(f64::MAX, f64::min) as usize, corners.iter().map(|c| c[0]).fold(0.0, f64::max) as usize);
    let (y0, y1) = (corners.iter().map(|c| c[1]).fold(f64::MAX, f64::min) as usize, corners.iter().map(|c| c[1]).fold(0.0, f64::max) as usize);
    let mut carded = photos[1].clone_photo();
    carded.path = dir.path().join("carded.jpg");
    for y in y0..y1 {
        carded.rgb.data[3 * (y * W + x0)..3 * (y * W + x1)].fill(110);
    }
    let e = err(&[photos[0].clone_photo(), carded, photos[2].clone_photo()]);
    let share: f64 = e.strip_prefix("carded.jpg: ").and_then(|r| r.split('%').next()).and_then(|p| p.parse().ok()).unwrap_or_else(|| panic!("{e}"));
    assert!((40.0..=65.0).contains(&share) && e.contains("take it again"), "{e}");

    // Nothing was written by any of them, and a good capture still works.
    assert!(!out.exists());
    photos.truncate(2);
    assert!(capture(&photos, &cfg, |_, _, _| {}).is_ok());
}

impl FramePhoto {
    #[cfg(feature = "raw")]
    fn clone_photo_with_raw(&self) -> FramePhoto {
        let raw = self.raw.as_ref().map(|r| RawPixels { linear: r.linear.clone(), baseline_gain: r.baseline_gain });
        FramePhoto { raw, ..self.clone_photo() }
    }

    fn clone_photo(&self) -> FramePhoto {
        FramePhoto { path: self.path.clone(), rgb: Rgb8 { width: self.rgb.width, height: self.rgb.height, data: self.rgb.data.clone() }, exif_focal: self.exif_focal, orientation: self.orientation, exposure: self.exposure.clone(), raw: None }
    }
}

#[test]
fn flash_offsets_turn_with_the_photo() {
    // A stored 3x2 photo with a dot at (row 0, col 0) and one at (row 0,
    // col 1): the vector between them is (+1, 0); after `oriented`, the
    // vector between the dots is what `oriented_offset` says.
    let mut image = crate::image::Image::new(1, 2, 3);
    image.set(0, 0, 0, 1.0);
    image.set(0, 0, 1, 2.0);
    let image_pos = |im: &crate::image::Image, v: f32| {
        let i = im.data.iter().position(|&x| x == v).unwrap();
        [(i % im.width) as f64, (i / im.width) as f64]
    };
    for o in 1..=8u16 {
        let turned = image.oriented(o);
        let (a, b) = (image_pos(&turned, 1.0), image_pos(&turned, 2.0));
        assert_eq!(oriented_offset([1.0, 0.0], o), [b[0] - a[0], b[1] - a[1]], "orientation {o}");
    }
    let mut image = crate::image::Image::new(1, 3, 2);
    image.set(0, 0, 0, 1.0);
    image.set(0, 1, 0, 2.0);
    for o in 1..=8u16 {
        let turned = image.oriented(o);
        let (a, b) = (image_pos(&turned, 1.0), image_pos(&turned, 2.0));
        assert_eq!(oriented_offset([0.0, 1.0], o), [b[0] - a[0], b[1] - a[1]], "orientation {o}");
    }
}

#[test]
fn the_frame_picture_has_its_tags_and_caption_room() {
    let layout = FrameLayout::new(10).unwrap();
    let (image, caption) = frame::frame_raster(&layout, frame::Paper::A4, 100.0).unwrap();
    // A4 at 100 dpi: 827 x 1169 pixels.
    assert_eq!((image.width, image.height), (827, 1169));
    let ink = image.data.iter().filter(|&&v| v < 0.5).count() as f64 / image.data.len() as f64;
    assert!(ink > 0.02 && ink < 0.2, "{ink}");
    // The caption under the scale bar, inside the page.
    assert_eq!(caption.len(), 3);
    assert!(caption.iter().all(|(_, [x, y])| *x > 0.0 && *y < image.height as f64 && *y > image.height as f64 / 2.0));
    // The detector finds every tag of the printed page.
    let rgb = Rgb8 { width: image.width, height: image.height, data: image.data.iter().flat_map(|&v| [crate::spaces::quantize_u8(v); 3]).collect() };
    let photo = FramePhoto { path: "frame.png".into(), rgb, exif_focal: None, orientation: 1, exposure: None, raw: None };
    let (found_layout, found) = find_frame(&photo, 2).unwrap();
    assert_eq!(found_layout, layout);
    assert_eq!(found.len(), layout.tags.len());
}

#[test]
fn sharpness_falls_with_blur_and_ignores_noise() {
    // A black-white step, blurred by sigma, with and without noise.
    let step = |sigma: f64, noise: f64| {
        let image = crate::image::Image::from_fn(1, 64, 64, |_, _, x| if x < 32 { 0.05 } else { 0.8 });
        let fx = PhoneEffects { blur_px: sigma, noise, jpeg_quality: None, seed: 1 };
        let rgb = as_phone_photo(&crate::image::Image::concat_channels(&[&image, &image, &image]).unwrap(), &fx).unwrap();
        let values = rgb.gray();
        markers::sharpness(&Gray { width: 64, height: 64, values: &values })
    };
    let sharp = step(0.0, 0.0);
    assert!((sharp - 0.5).abs() < 0.01, "{sharp}");
    for sigma in [1.5f64, 3.0, 6.0] {
        let s = step(sigma, 0.004);
        // A Gaussian edge's steepest slope: spread / (sigma sqrt(2 pi)), and
        // the sRGB curve steepens the dark side a little.
        let expect = 1.0 / (sigma * (2.0 * std::f64::consts::PI).sqrt());
        assert!(s > 0.8 * expect && s < 2.0 * expect, "sigma {sigma}: {s} against {expect}");
    }
    assert!(step(6.0, 0.004) < BLURRED_BELOW && step(1.5, 0.004) > BLURRED_BELOW);
}

#[test]
fn tags_of_another_family_are_named() {
    // Six tag25h9 tags (9 x 9 cells with their white ring), 12 pixels a cell, on white paper.
    let (w, h, cell) = (720usize, 360usize, 12usize);
    let mut gray = vec![235u8; w * h];
    // SAFETY: the family and each tag image are created, read within their size and destroyed here.
    unsafe {
        let family = apriltag_sys::tag25h9_create();
        for id in 0..6 {
            let image = apriltag_sys::apriltag_to_image(family, id);
            let (side, stride) = ((*image).width as usize, (*image).stride as usize);
            let (left, top) = (30 + (id as usize % 3) * 230, 30 + (id as usize / 3) * 170);
            for y in 0..side * cell {
                for x in 0..side * cell {
                    gray[(top + y) * w + left + x] = if *(*image).buf.add((y / cell) * stride + x / cell) > 127 { 235 } else { 20 };
                }
            }
            apriltag_sys::image_u8_destroy(image);
        }
        apriltag_sys::tag25h9_destroy(family);
    }
    let rgb = Rgb8 { width: w, height: h, data: gray.iter().flat_map(|&v| [v; 3]).collect() };
    let photo = FramePhoto { path: "other.png".into(), rgb, exif_focal: None, orientation: 1, exposure: None, raw: None };
    let e = format!("{:#}", find_frame(&photo, 2).err().expect("an error"));
    assert!(e.starts_with("other.png: its tags are tag25h9, not the frame's tag36h11"), "{e}");
}

#[test]
fn differing_exposures_are_brought_to_one_or_named() {
    use crate::infer::camera::Exposure;
    let photo = |name: &str, exposure: Option<Exposure>| FramePhoto { path: name.into(), rgb: Rgb8 { width: 1, height: 1, data: vec![0; 3] }, exif_focal: None, orientation: 1, exposure, raw: None };
    let stated = |t: f64, n: f64, iso: u32| Some(Exposure { time_s: Some(t), f_number: Some(n), iso: Some(iso) });
    let same = [photo("a.jpg", stated(1.0 / 60.0, 1.8, 100)), photo("b.jpg", stated(1.0 / 60.0, 1.8, 100))];
    assert_eq!(exposure_warning(&same), None);
    assert_eq!(relative_exposures(&same), None);
    assert_eq!(exposure_warning(&[photo("a.jpg", None), photo("b.jpg", None)]), None);
    // Bracketed: half the time and twice the ISO is the same exposure; f/2.55 is half of f/1.8's.
    let bracket = [photo("a.jpg", stated(1.0 / 60.0, 1.8, 100)), photo("b.jpg", stated(1.0 / 120.0, 1.8, 200)), photo("c.jpg", stated(1.0 / 60.0, 1.8 * 2f64.sqrt(), 100))];
    let rel = relative_exposures(&bracket).unwrap();
    assert_eq!(rel.len(), 3);
    assert!((rel[0] - 1.0).abs() < 1e-12 && (rel[1] - 1.0).abs() < 1e-12 && (rel[2] - 0.5).abs() < 1e-12, "{rel:?}");
    assert_eq!(exposure_warning(&bracket), None);
    // A photo that does not state its ISO: the exposures cannot be brought to one.
    let partial = [photo("a.jpg", stated(1.0 / 60.0, 1.8, 100)), photo("b.jpg", Some(Exposure { time_s: Some(1.0 / 120.0), f_number: Some(1.8), iso: None }))];
    assert_eq!(relative_exposures(&partial), None);
    let w = exposure_warning(&partial).unwrap();
    assert!(w.starts_with("the photos' exposures differ (a.jpg 1/60 s, f/1.8, ISO 100, b.jpg 1/120 s, f/1.8) and not every photo states"), "{w}");
}

#[test]
fn straight_on_photos_without_exif_have_no_focal_length() {
    // Two photos facing the frame straight on (one off to the side), with no
    // EXIF: their perspective cannot fix the focal length, and the capture
    // says so instead of guessing.
    let dir = tempfile::tempdir().unwrap();
    let mut v = phone_views(&[[0.0, 0.0, 260.0], [2.0, -1.0, 255.0]], &[0.0, 3.0], W, H, FOCAL, 0.0, 0.0);
    v[1].pose = camera::Pose::look_at([30.0, -20.0, 255.0], [30.0, -20.0, 0.0], [0.0, 1.0, 0.0]);
    let fx = PhoneEffects { jpeg_quality: None, ..Default::default() };
    let (mut photos, _) = shoot(&v, [0.0, 0.0], fx, dir.path());
    for p in &mut photos {
        p.exif_focal = None;
    }
    let e = format!("{:#}", capture(&photos, &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.starts_with("no focal length: the photos have no EXIF focal length, and none looks at the frame at a slant"), "{e}");
    // With the EXIF's focal length the same photos are a capture, at that
    // focal length (the tags cannot move it: straight on, it trades with
    // the distance; left free, noise once took it past the EXIF's by 15%
    // and the photos were refused as cropped), so the lens at its height.
    for p in &mut photos {
        p.exif_focal = Some(FOCAL);
    }
    let cap = capture(&photos, &CaptureConfig::default(), |_, _, _| {}).unwrap();
    assert_eq!(cap.photos[0].intrinsics.focal, FOCAL);
    assert!((cap.photos[0].camera[2] - 260.0).abs() < 2.0, "lens at {:?}", cap.photos[0].camera);
}

/// `photo` at half its width and height (2x2 means of its codes), as a
/// messenger sends it on.
fn halved(photo: &FramePhoto) -> FramePhoto {
    let (w, h) = (photo.rgb.width / 2, photo.rgb.height / 2);
    let src = &photo.rgb.data;
    let at = |x: usize, y: usize, c: usize| src[3 * (y * photo.rgb.width + x) + c] as u32;
    let data = (0..h).flat_map(|y| (0..w).flat_map(move |x| (0..3).map(move |c| ((at(2 * x, 2 * y, c) + at(2 * x + 1, 2 * y, c) + at(2 * x, 2 * y + 1, c) + at(2 * x + 1, 2 * y + 1, c) + 2) / 4) as u8))).collect();
    FramePhoto { rgb: super::rectify::Rgb8 { width: w, height: h, data }, exif_focal: None, ..photo.clone_photo() }
}

#[test]
fn a_downscaled_or_turned_photo_without_exif_keeps_its_position_and_a_cropped_or_repeated_one_is_named() {
    // Photo 0 (overhead) sent on at half size without its EXIF: one lens,
    // its focal length in pixels halved with the photo. Fitted with one
    // focal length in pixels for all, it put that lens 260 mm off.
    let dir = tempfile::tempdir().unwrap();
    let views = views(0.0);
    let (mut photos, _) = shoot(&views, [0.0, 0.0], PhoneEffects { jpeg_quality: None, ..Default::default() }, dir.path());
    photos[0] = halved(&photos[0]);
    let cap = capture(&photos, &CaptureConfig::default(), |_, _, _| {}).unwrap();
    for (result, view) in cap.photos.iter().zip(&views) {
        let d = length(sub(result.camera, view.pose.centre()));
        eprintln!("{}: camera {d:.2} mm off, focal {:.1} px", result.source.display(), result.intrinsics.focal);
        assert!(d < 3.0, "{}: camera {d:.2} mm off", result.source.display());
    }
    let small = cap.photos.iter().find(|r| r.source == photos[0].path).unwrap();
    assert!((small.intrinsics.focal / (FOCAL / 2.0) - 1.0).abs() < 0.02, "the halved photo's focal length {}", small.intrinsics.focal);
    // No photo with EXIF: the tilted photos' perspective gives the focal length, for both sizes.
    for p in &mut photos {
        p.exif_focal = None;
    }
    let cap = capture(&photos, &CaptureConfig::default(), |_, _, _| {}).unwrap();
    for (result, view) in cap.photos.iter().zip(&views) {
        let d = length(sub(result.camera, view.pose.centre()));
        assert!(d < 3.0, "without EXIF, {}: camera {d:.2} mm off", result.source.display());
    }
    // A photo turned a quarter, its EXIF lost (portrait among landscape): the same lens.
    let mut turned = photos.iter().map(|p| p.clone_photo()).collect::<Vec<_>>();
    let t = &mut turned[2].rgb;
    let (w, h) = (t.width, t.height);
    // Clockwise: the new pixel (x, y) is the old (y, h - 1 - x).
    let data = (0..w).flat_map(|y| (0..h).flat_map(move |x| (0..3).map(move |c| (y, x, c)))).map(|(y, x, c)| t.data[3 * ((h - 1 - x) * w + y) + c]).collect();
    *t = super::rectify::Rgb8 { width: h, height: w, data };
    let cap = capture(&turned, &CaptureConfig::default(), |_, _, _| {}).unwrap();
    for (result, view) in cap.photos.iter().zip(&views) {
        let d = length(sub(result.camera, view.pose.centre()));
        assert!(d < 3.0, "with {} turned, {}: camera {d:.2} mm off", turned[2].path.display(), result.source.display());
    }
    // The same photo twice, or a copy under another name: named.
    let mut twice = photos.iter().map(|p| p.clone_photo()).collect::<Vec<_>>();
    twice.push(photos[1].clone_photo());
    let e = format!("{:#}", capture(&twice, &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.contains("IMG_1.jpg: given twice"), "{e}");
    twice.last_mut().unwrap().path = dir.path().join("copy.jpg");
    let e = format!("{:#}", capture(&twice, &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.contains("copy.jpg: the same pixels as IMG_1.jpg"), "{e}");
    // An EXIF focal length the tags contradict (another lens's EXIF, or a zoomed photo): the photo named.
    let mut zoomed = photos.iter().map(|p| p.clone_photo()).collect::<Vec<_>>();
    zoomed[0].exif_focal = Some(FOCAL * 3.0);
    let e = format!("{:#}", capture(&zoomed, &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.starts_with("IMG_0.jpg: its EXIF says a focal length of"), "{e}");
    // A grey photo among colour ones (a black-and-white mode): named by the file given.
    let mut grey = photos.iter().map(|p| p.clone_photo()).collect::<Vec<_>>();
    for px in grey[1].rgb.data.chunks_mut(3) {
        let mean = ((px[0] as u32 + px[1] as u32 + px[2] as u32) / 3) as u8;
        px.fill(mean);
    }
    let e = format!("{:#}", capture(&grey, &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.starts_with("IMG_1.jpg: the photo is grey"), "{e}");
    // A photo cropped to another shape: named.
    let mut cropped = photos[1].clone_photo();
    let (w, h) = (cropped.rgb.width, cropped.rgb.height);
    cropped.rgb = super::rectify::Rgb8 { width: h, height: h, data: (0..h).flat_map(|y| cropped.rgb.data[3 * (y * w + (w - h) / 2)..3 * (y * w + (w + h) / 2)].to_vec()).collect() };
    photos[1] = cropped;
    let e = format!("{:#}", capture(&photos, &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.contains("IMG_1.jpg") && e.contains("900x900") && e.contains("cropped") && !e.contains('\n'), "{e}");
}

#[test]
fn a_grey_material_with_a_white_balance_cast_in_one_photo_is_not_refused_as_grey() {
    // Grey kd and ks; photo 1 taken with a warm cast (R x1.15, B x0.85, as
    // auto white balance does). Unbalanced, photo 1 shows colour (0.1) and
    // the others none, so the grey-photo check would refuse them; the
    // paper's levels take the cast out first.
    let dir = tempfile::tempdir().unwrap();
    let mut maps = material().stacked();
    for c in 0..6 {
        let grey = if c < 3 { 0.2 } else { 0.05 };
        for y in 0..maps.height {
            for x in 0..maps.width {
                maps.set(c, y, x, grey);
            }
        }
    }
    let grey = crate::svbrdf::Svbrdf::from_stacked(&maps).unwrap();
    let layout = FrameLayout::new(10).unwrap();
    let fx = PhoneEffects { jpeg_quality: None, ..Default::default() };
    let views = views(0.0);
    let shots = super::synthetic::shoot(&grey, &layout, &views[..3], [0.0, 0.0], super::synthetic::SUPERSAMPLE, &fx).unwrap();
    let mut photos: Vec<FramePhoto> = shots.into_iter().enumerate().map(|(i, s)| FramePhoto { path: dir.path().join(format!("IMG_{i}.jpg")), rgb: s.rgb, exif_focal: Some(FOCAL), orientation: 1, exposure: None, raw: None }).collect();
    let cast = [1.15f32, 1.0, 0.85];
    for (k, v) in photos[1].rgb.data.iter_mut().enumerate() {
        *v = crate::spaces::quantize_u8(crate::spaces::photo_encode((crate::spaces::photo_decode(*v as f32 / 255.0) * cast[k % 3]).min(1.0)));
    }
    let cap = capture(&photos, &CaptureConfig::default(), |_, _, _| {}).unwrap();
    let levels = super::photometry::relative_levels(&cap.paper).unwrap();
    assert!((levels[1][0] / levels[1][2] - 1.15 / 0.85).abs() < 0.1, "the cast read by the paper: {:?}", levels[1]);
}

#[test]
fn the_picture_of_many_photos_wraps_its_rows_and_says_how_many_it_shows() {
    // 50 photos (the 4 of a capture, repeated): 8 to a row, the first 48
    // shown in 6 rows of photos over their openings; 180 in one row made a
    // picture 65,888 pixels wide.
    let dir = tempfile::tempdir().unwrap();
    let (photos, _) = shoot(&views(0.0), [0.0, 0.0], PhoneEffects { jpeg_quality: None, ..Default::default() }, dir.path());
    let mut cap = capture(&photos, &CaptureConfig::default(), |_, _, _| {}).unwrap();
    let n = cap.photos.len();
    cap.photos = (0..50).map(|i| cap.photos[i % n].clone()).collect();
    cap.rectified = (0..50).map(|i| cap.rectified[i % n].clone()).collect();
    cap.paper = (0..50).map(|i| cap.paper[i % n].clone()).collect();
    let picture = super::pictures::capture_picture(&cap, &photos).unwrap();
    // Cells of 360 pixels (the thumbnails' longer side and the top view) and 4-pixel gaps.
    let cell = 360 + 4;
    assert_eq!((picture.width, picture.height), (9 * cell + 4, 12 * cell + 4));
}

#[test]
fn an_exposure_no_phone_takes_is_named_before_any_work() {
    let mut photo = FramePhoto { path: "IMG_7.jpg".into(), rgb: super::rectify::Rgb8 { width: 2, height: 2, data: vec![0; 12] }, exif_focal: None, orientation: 1, exposure: None, raw: None };
    let exposure = |t: f64, iso: u32| Some(crate::infer::camera::Exposure { time_s: Some(t), f_number: Some(1.8), iso: Some(iso) });
    photo.exposure = exposure(1.0 / 60.0, 100);
    assert!(check_exif_exposure(&photo).is_ok());
    for (t, iso) in [(4e9, 100), (1.0 / 60.0, 0), (1e-9, 100)] {
        photo.exposure = exposure(t, iso);
        let e = format!("{:#}", check_exif_exposure(&photo).unwrap_err());
        assert!(e.starts_with("IMG_7.jpg: its EXIF states an exposure no phone takes") && !e.contains('\n'), "{e}");
    }
    // capture refuses it before looking for tags (the 2x2 photo has none).
    photo.exposure = exposure(4e9, 100);
    let e = format!("{:#}", capture(&[photo.clone_photo(), photo.clone_photo()], &CaptureConfig::default(), |_, _, _| {}).err().expect("an error"));
    assert!(e.contains("no phone takes"), "{e}");
}

#[cfg(feature = "raw")]
#[test]
fn raw_photos_of_the_frame_make_a_raw_capture_and_are_not_mixed_with_jpegs() {
    // The four phone photos saved as linear 12-bit DNGs (26 mm equivalent,
    // as FOCAL): found, fitted and rectified from their linear values, the
    // folder's photos written as 16-bit linear DNGs that the fit reads.
    let dir = tempfile::tempdir().unwrap();
    let views = views(0.0);
    let fx = PhoneEffects { jpeg_quality: None, ..Default::default() };
    let (photos, truths) = shoot(&views, [8.0, -3.0], fx, dir.path());
    let opts = crate::io::dng::DngOptions { focal_35mm: Some(26), baseline_exposure: 1.0, ..Default::default() };
    let raws: Vec<FramePhoto> = photos
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let linear = p.rgb.to_image().map(crate::spaces::photo_decode);
            let path = dir.path().join(format!("IMG_{i}.dng"));
            crate::io::dng::write_dng(&path, &linear, &opts).unwrap();
            load_frame_photo(&path).unwrap()
        })
        .collect();
    assert!(raws.iter().all(|p| p.raw.as_ref().is_some_and(|r| (r.baseline_gain - 2.0).abs() < 1e-6)));
    assert!((raws[0].exif_focal.unwrap() / FOCAL - 1.0).abs() < 0.01, "focal {:?}", raws[0].exif_focal);
    let cfg = CaptureConfig { flash_offset_mm: [8.0, -3.0], ..Default::default() };
    let cap = capture(&raws, &cfg, |_, _, _| {}).unwrap();
    for (n, rect) in cap.rectified.iter().enumerate() {
        let truth = truths[n].resize_bilinear(cap.side, cap.side);
        let err = rect.iter().zip(&truth.data).map(|(a, b)| (a - b).abs() as f64).sum::<f64>() / rect.len() as f64;
        let level = truth.data.iter().map(|&v| v as f64).sum::<f64>() / rect.len() as f64;
        assert!(err < 0.12 * level, "photo {n}: mean error {err:.4} on a level of {level:.4}");
    }
    let out = dir.path().join("capture");
    write_folder(&cap, &out, &raws).unwrap();
    assert!(out.join("00.dng").is_file() && !out.join("00.png").exists());
    let folder = crate::data::captures::Captures::open(&out).unwrap();
    assert_eq!(folder.raw_gains, [2.0; 4]);
    // The folder's photo reads back as what was rectified (16 bits).
    let back = crate::data::captures::load_photo(&folder.photos[0], cap.side).unwrap();
    let rect = tch::Tensor::from_slice(&cap.rectified[0]).view([3, cap.side as i64, cap.side as i64]);
    let d = (back - rect).abs().max().double_value(&[]);
    assert!(d < 1e-4, "the written DNG is {d} off the rectified photo");
    // One RAW photo among JPEGs: refused, naming both.
    let mixed = vec![raws[0].clone_photo_with_raw(), photos[1].clone_photo(), photos[2].clone_photo()];
    let e = format!("{:#}", capture(&mixed, &cfg, |_, _, _| {}).err().expect("a mixed capture is refused"));
    assert!(e.contains("IMG_0.dng") && e.contains("IMG_1.jpg") && e.contains("RAW"), "{e}");
}

#[test]
fn a_tone_mapped_photo_is_named_by_its_paper() {
    // Photo 3 (the most tilted, its paper lit from 1 to 1.3) through a
    // curve that flattens its contrast (linear^0.5, as local tone mapping
    // does to a gradient): its paper no longer follows the flash.
    let dir = tempfile::tempdir().unwrap();
    let views = views(0.0);
    let (mut photos, _) = shoot(&views, [8.0, -3.0], PhoneEffects::default(), dir.path());
    photos[3].rgb.data.iter_mut().for_each(|code| {
        *code = crate::spaces::quantize_u8(crate::spaces::photo_encode(0.6 * crate::spaces::photo_decode(*code as f32 / 255.0).sqrt()));
    });
    let cfg = CaptureConfig { flash_offset_mm: [8.0, -3.0], ..Default::default() };
    let cap = capture(&photos, &cfg, |_, _, _| {}).unwrap();
    let slopes: Vec<Option<f64>> = cap.paper.iter().map(|r| r.response_slope).collect();
    eprintln!("response slopes {slopes:?}");
    let warnings = photometry::warnings(&cap.photos, &cap.paper);
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].starts_with("IMG_3.jpg: the frame's paper does not brighten"), "{warnings:?}");
    // The others' slopes, where stated, near 1.
    for (p, s) in cap.photos.iter().zip(&slopes) {
        if p.source != photos[3].path {
            assert!(s.is_none_or(|s| (s - 1.0).abs() < 0.2), "{}: slope {s:?}", p.source.display());
        }
    }
}

#[test]
fn a_tone_curve_that_is_not_srgb_is_measured_by_the_paper_and_undone() {
    // Every photo through a pure 2.4 gamma where the reader assumes sRGB
    // (a phone's own curve): decoded as sRGB, the light comes out near its
    // 0.92th power near white, and up to twice as bright in the dark. The
    // tilted photos' paper measures the gamma, and the rectified openings
    // come back to the clean capture's.
    let dir = tempfile::tempdir().unwrap();
    let views = views(0.0);
    let fx = PhoneEffects { jpeg_quality: None, ..Default::default() };
    let (clean, _) = shoot(&views, [8.0, -3.0], fx, dir.path());
    let curved: Vec<FramePhoto> = clean
        .iter()
        .map(|p| {
            let mut p = p.clone_photo();
            p.rgb.data.iter_mut().for_each(|code| *code = crate::spaces::quantize_u8(crate::spaces::photo_decode(*code as f32 / 255.0).powf(1.0 / 2.4)));
            p
        })
        .collect();
    let cfg = CaptureConfig { flash_offset_mm: [8.0, -3.0], ..Default::default() };
    let reference = capture(&clean, &cfg, |_, _, _| {}).unwrap();
    assert_eq!(reference.gamma, None);
    let cap = capture(&curved, &cfg, |_, _, _| {}).unwrap();
    let gamma = cap.gamma.expect("the paper states the curve");
    assert!((2.3..2.5).contains(&gamma), "gamma {gamma}");
    assert!(photometry::warnings(&cap.photos, &cap.paper).is_empty());
    // Mean |ln| ratio to the clean openings over the pixels both see above
    // the darkest (ln of the 8-bit codes' steps is noisy there).
    let log_error = |rect: &[f32], clean: &[f32], read: &dyn Fn(f32) -> f32| {
        let pairs: Vec<f64> = rect.iter().zip(clean).filter(|(_, &c)| c > 0.02).map(|(&r, &c)| (read(r) as f64 / c as f64).ln().abs()).collect();
        pairs.iter().sum::<f64>() / pairs.len() as f64
    };
    let as_srgb = |linear: f32| crate::spaces::photo_decode(linear.powf(1.0 / gamma as f32)); // what the sRGB reading gave
    for n in 0..cap.rectified.len() {
        let corrected = log_error(&cap.rectified[n], &reference.rectified[n], &|v| v);
        let as_decoded = log_error(&cap.rectified[n], &reference.rectified[n], &as_srgb);
        eprintln!("photo {n}: gamma {gamma:.3}, ln error {corrected:.4} corrected, {as_decoded:.4} as decoded");
        assert!(corrected < 0.1 * as_decoded && corrected < 0.01, "photo {n}: ln error {corrected:.4} corrected, {as_decoded:.4} as decoded");
    }
}

#[test]
fn a_mirrored_photo_is_named_as_mirrored() {
    // The overhead photo flipped left to right (a front camera's selfie, or
    // an editor's flip): its tags read only mirrored. It once got "no frame
    // tags found".
    let dir = tempfile::tempdir().unwrap();
    let v = phone_views(&[[0.0, 0.0, 260.0]], &[0.0], W, H, FOCAL, 0.0, 0.0);
    let (photos, _) = shoot(&v, [0.0, 0.0], PhoneEffects { jpeg_quality: None, ..Default::default() }, dir.path());
    let p = &photos[0];
    let data = p.rgb.data.chunks_exact(3 * W).flat_map(|row| row.chunks_exact(3).rev().flatten().copied().collect::<Vec<u8>>()).collect();
    let mirrored = FramePhoto { rgb: Rgb8 { width: W, height: H, data }, ..p.clone_photo() };
    let e = format!("{:#}", find_frame(&mirrored, 2).err().expect("an error"));
    assert!(e.starts_with("IMG_0.jpg: the photo is mirrored"), "{e}");
    assert!(find_frame(p, 2).is_ok());
}
