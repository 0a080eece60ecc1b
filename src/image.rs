//! A plain floating-point image: planar channels, row-major, no tensor library.
//!
//! Layout is `[C, H, W]` (channel planes one after another), the layout that
//! tensors use, so converting to and from `tch::Tensor` is a reshape.

use anyhow::{bail, Result};

/// A `[C, H, W]` float image. Values are in whatever space the owner says
/// (linear radiance, gamma-encoded, log); see `crate::spaces`.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub channels: usize,
    pub height: usize,
    pub width: usize,
    /// `channels * height * width` values, channel-major.
    pub data: Vec<f32>,
}

/// Whether every value of a float tensor (any shape, kind or device) is
/// finite: the check before anything computed is written.
pub fn all_finite(t: &tch::Tensor) -> bool {
    t.numel() == 0 || t.isfinite().all().int64_value(&[]) != 0
}

impl Image {
    pub fn new(channels: usize, height: usize, width: usize) -> Self {
        Self { channels, height, width, data: vec![0.0; channels * height * width] }
    }

    pub fn filled(channels: usize, height: usize, width: usize, value: f32) -> Self {
        Self { channels, height, width, data: vec![value; channels * height * width] }
    }

    pub fn from_data(channels: usize, height: usize, width: usize, data: Vec<f32>) -> Result<Self> {
        if data.len() != channels * height * width {
            bail!("image data has {} values, expected {}x{}x{}", data.len(), channels, height, width);
        }
        Ok(Self { channels, height, width, data })
    }

    /// Builds an image by evaluating `f(channel, row, col)` at every sample.
    pub fn from_fn(channels: usize, height: usize, width: usize, f: impl Fn(usize, usize, usize) -> f32) -> Self {
        let mut data = Vec::with_capacity(channels * height * width);
        for c in 0..channels {
            for y in 0..height {
                for x in 0..width {
                    data.push(f(c, y, x));
                }
            }
        }
        Self { channels, height, width, data }
    }

    #[inline]
    pub fn index(&self, c: usize, y: usize, x: usize) -> usize {
        (c * self.height + y) * self.width + x
    }

    #[inline]
    pub fn get(&self, c: usize, y: usize, x: usize) -> f32 {
        self.data[self.index(c, y, x)]
    }

    #[inline]
    pub fn set(&mut self, c: usize, y: usize, x: usize, v: f32) {
        let i = self.index(c, y, x);
        self.data[i] = v;
    }

    /// One channel plane as a slice of `H * W` values.
    pub fn plane(&self, c: usize) -> &[f32] {
        let n = self.height * self.width;
        &self.data[c * n..(c + 1) * n]
    }

    pub fn plane_mut(&mut self, c: usize) -> &mut [f32] {
        let n = self.height * self.width;
        &mut self.data[c * n..(c + 1) * n]
    }

    /// The pixel at (y, x) as a `channels`-long vector.
    pub fn pixel(&self, y: usize, x: usize) -> Vec<f32> {
        (0..self.channels).map(|c| self.get(c, y, x)).collect()
    }

    pub fn map(&self, f: impl Fn(f32) -> f32) -> Self {
        Self { data: self.data.iter().map(|&v| f(v)).collect(), ..*self }
    }

    /// The image as it should be shown given its EXIF orientation tag
    /// (1: as stored; 2/4 mirrored; 3 turned 180 degrees; 6 and 8 turned 90
    /// degrees clockwise and counter-clockwise; 5/7 transposed). Tags 5-8
    /// swap height and width; other values leave the image as it is.
    pub fn oriented(&self, orientation: u16) -> Self {
        let (h, w) = (self.height, self.width);
        let (oh, ow) = if (5..=8).contains(&orientation) { (w, h) } else { (h, w) };
        // Source (row, column) of output pixel (r, c).
        let source = |r: usize, c: usize| match orientation {
            2 => (r, w - 1 - c),
            3 => (h - 1 - r, w - 1 - c),
            4 => (h - 1 - r, c),
            5 => (c, r),
            6 => (h - 1 - c, r),
            7 => (h - 1 - c, w - 1 - r),
            8 => (c, w - 1 - r),
            _ => (r, c),
        };
        Self::from_fn(self.channels, oh, ow, |ch, r, c| {
            let (sr, sc) = source(r, c);
            self.get(ch, sr, sc)
        })
    }

    /// A linear image as the 8-bit picture values flashmat writes
    /// ([`crate::spaces::photo_encode`], the sRGB curve `estimate` decodes).
    pub fn to_display(&self) -> Self {
        self.map(crate::spaces::photo_encode)
    }

    /// Picture of a linear render, as [`Image::to_display`]
    /// ([`crate::spaces::linear_to_photo`]). linear: `[3, H, W]`.
    pub fn display_of(linear: &tch::Tensor) -> anyhow::Result<Self> {
        Self::from_tensor(&crate::spaces::linear_to_photo(linear))
    }

    /// Rectangular crop: rows `top..top+h`, columns `left..left+w`.
    /// One of the 8 symmetries of the square grid: bit 0 reverses the
    /// columns, bit 1 the rows, bit 2 then swaps rows and columns
    /// (`[C, H, W]` -> `[C, W, H]`).
    pub fn dihedral(&self, code: u8) -> Self {
        let (h, w) = (self.height, self.width);
        let at = |c: usize, y: usize, x: usize| {
            let x = if code & 1 != 0 { w - 1 - x } else { x };
            let y = if code & 2 != 0 { h - 1 - y } else { y };
            self.get(c, y, x)
        };
        if code & 4 != 0 {
            Self::from_fn(self.channels, w, h, |c, y, x| at(c, x, y))
        } else {
            Self::from_fn(self.channels, h, w, at)
        }
    }

    pub fn crop(&self, top: usize, left: usize, h: usize, w: usize) -> Result<Self> {
        if top + h > self.height || left + w > self.width {
            bail!(
                "crop {}x{} at ({}, {}) does not fit in a {}x{} image",
                w, h, left, top, self.width, self.height
            );
        }
        Ok(Self::from_fn(self.channels, h, w, |c, y, x| self.get(c, top + y, left + x)))
    }

    /// Columns `left..left+w` of every row (used to cut strip images into panels).
    pub fn columns(&self, left: usize, w: usize) -> Result<Self> {
        self.crop(0, left, self.height, w)
    }

    /// Selects channels `first..first+count`.
    pub fn channel_range(&self, first: usize, count: usize) -> Result<Self> {
        if first + count > self.channels {
            bail!("channels {}..{} requested from a {}-channel image", first, first + count, self.channels);
        }
        let n = self.height * self.width;
        Ok(Self {
            channels: count,
            height: self.height,
            width: self.width,
            data: self.data[first * n..(first + count) * n].to_vec(),
        })
    }

    /// Stacks images with equal H, W along the channel axis.
    pub fn concat_channels(images: &[&Image]) -> Result<Self> {
        let Some(first) = images.first() else { bail!("no images to concatenate") };
        let mut data = Vec::new();
        let mut channels = 0;
        for im in images {
            if im.height != first.height || im.width != first.width {
                bail!("cannot stack a {}x{} image with a {}x{} image", im.width, im.height, first.width, first.height);
            }
            data.extend_from_slice(&im.data);
            channels += im.channels;
        }
        Ok(Self { channels, height: first.height, width: first.width, data })
    }

    /// Anti-aliased shrink: every output pixel is the mean of the source area
    /// it covers (a box filter of exactly the output pixel's footprint), so
    /// no detail aliases into a model input. Separable; `h <= height` and
    /// `w <= width` (enlarging is refused by the callers).
    pub fn resize_area(&self, h: usize, w: usize) -> Image {
        let image = self;
        assert!(h <= image.height && w <= image.width && h > 0 && w > 0, "resize_area only shrinks");
        if (h, w) == (image.height, image.width) {
            return image.clone();
        }
        let (wx, wy) = (area_weights(image.width, w), area_weights(image.height, h));
        // Columns first: [C, H, w].
        let mut tmp = Image::new(image.channels, image.height, w);
        for c in 0..image.channels {
            for y in 0..image.height {
                let row = &image.plane(c)[y * image.width..(y + 1) * image.width];
                for (x, (first, ws)) in wx.iter().enumerate() {
                    let v: f32 = ws.iter().enumerate().map(|(k, wk)| wk * row[first + k]).sum();
                    tmp.set(c, y, x, v);
                }
            }
        }
        let mut out = Image::new(image.channels, h, w);
        for c in 0..image.channels {
            for (y, (first, ws)) in wy.iter().enumerate() {
                for x in 0..w {
                    let v: f32 = ws.iter().enumerate().map(|(k, wk)| wk * tmp.get(c, first + k, x)).sum();
                    out.set(c, y, x, v);
                }
            }
        }
        out
    }

    /// Resize to `h x w`: area average when shrinking (both sides no
    /// larger than now), bilinear otherwise.
    pub fn resize_to(&self, h: usize, w: usize) -> Self {
        if h <= self.height && w <= self.width {
            self.resize_area(h, w)
        } else {
            self.resize_bilinear(h, w)
        }
    }

    /// Bilinear resize (pixel-centre aligned, as torch's `align_corners=false`).
    pub fn resize_bilinear(&self, h: usize, w: usize) -> Self {
        let sy = self.height as f32 / h as f32;
        let sx = self.width as f32 / w as f32;
        let mut out = Image::new(self.channels, h, w);
        for y in 0..h {
            let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, (self.height - 1) as f32);
            let y0 = fy.floor() as usize;
            let y1 = (y0 + 1).min(self.height - 1);
            let ty = fy - y0 as f32;
            for x in 0..w {
                let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, (self.width - 1) as f32);
                let x0 = fx.floor() as usize;
                let x1 = (x0 + 1).min(self.width - 1);
                let tx = fx - x0 as f32;
                for c in 0..self.channels {
                    let a = self.get(c, y0, x0) * (1.0 - tx) + self.get(c, y0, x1) * tx;
                    let b = self.get(c, y1, x0) * (1.0 - tx) + self.get(c, y1, x1) * tx;
                    out.set(c, y, x, a * (1.0 - ty) + b * ty);
                }
            }
        }
        out
    }

    /// Area-averaging resize by an integer factor (anti-aliased downsampling).
    pub fn downsample(&self, factor: usize) -> Self {
        let (h, w) = (self.height / factor, self.width / factor);
        let norm = 1.0 / (factor * factor) as f32;
        Self::from_fn(self.channels, h, w, |c, y, x| {
            let mut s = 0.0;
            for dy in 0..factor {
                for dx in 0..factor {
                    s += self.get(c, y * factor + dy, x * factor + dx);
                }
            }
            s * norm
        })
    }

    /// First non-finite sample as (channel, row, col), if any.
    pub fn find_non_finite(&self) -> Option<(usize, usize, usize)> {
        let n = self.height * self.width;
        self.data.iter().position(|v| !v.is_finite()).map(|i| (i / n, (i % n) / self.width, i % self.width))
    }

    /// As a `[C, H, W]` float tensor on the CPU.
    pub fn to_tensor(&self) -> tch::Tensor {
        tch::Tensor::from_slice(&self.data).view([self.channels as i64, self.height as i64, self.width as i64])
    }

    /// From a `[C, H, W]` (or `[1, C, H, W]`) tensor of any kind or device.
    pub fn from_tensor(t: &tch::Tensor) -> Result<Self> {
        let t = if t.dim() == 4 && t.size()[0] == 1 { t.squeeze_dim(0) } else { t.shallow_clone() };
        let size = t.size();
        if size.len() != 3 {
            bail!("expected a [C, H, W] tensor, got shape {size:?}");
        }
        let data: Vec<f32> = Vec::try_from(t.to_device(tch::Device::Cpu).to_kind(tch::Kind::Float).contiguous().flatten(0, -1))?;
        Self::from_data(size[0] as usize, size[1] as usize, size[2] as usize, data)
    }

    pub fn mean(&self) -> f32 {
        self.data.iter().map(|&v| v as f64).sum::<f64>() as f32 / self.data.len().max(1) as f32
    }
}

/// Exact area-averaging weights resampling `n` samples to `m <= n`: output
/// sample o averages the source interval [o n/m, (o+1) n/m), each source
/// sample weighted by its overlap. Returns (first source index, weights).
fn area_weights(n: usize, m: usize) -> Vec<(usize, Vec<f32>)> {
    let scale = n as f64 / m as f64;
    (0..m)
        .map(|o| {
            let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
            let first = a.floor() as usize;
            let last = (b.ceil() as usize).min(n);
            let w = (first..last).map(|i| ((b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0) / scale) as f32).collect();
            (first, w)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_channel_major() {
        let im = Image::from_fn(2, 3, 4, |c, y, x| (c * 100 + y * 10 + x) as f32);
        assert_eq!(im.get(1, 2, 3), 123.0);
        assert_eq!(im.data[im.index(1, 0, 0)], 100.0);
        assert_eq!(im.plane(1)[0], 100.0);
        assert_eq!(im.pixel(2, 1), vec![21.0, 121.0]);
    }

    #[test]
    fn crop_and_columns() {
        let im = Image::from_fn(1, 4, 6, |_, y, x| (y * 10 + x) as f32);
        let c = im.crop(1, 2, 2, 3).unwrap();
        assert_eq!(c.data, vec![12.0, 13.0, 14.0, 22.0, 23.0, 24.0]);
        assert!(im.crop(3, 0, 2, 2).is_err());
        assert_eq!(im.columns(4, 2).unwrap().get(0, 3, 1), 35.0);
    }

    #[test]
    fn resize_identity_and_constant() {
        let im = Image::from_fn(3, 8, 8, |c, y, x| (c + y * x) as f32);
        assert_eq!(im.resize_bilinear(8, 8), im);
        let k = Image::filled(1, 5, 7, 0.25).resize_bilinear(13, 3);
        assert!(k.data.iter().all(|&v| (v - 0.25).abs() < 1e-7));
        let d = Image::from_fn(1, 4, 4, |_, y, _| y as f32).downsample(2);
        assert_eq!(d.data, vec![0.5, 0.5, 2.5, 2.5]);
    }

    #[test]
    fn tensor_round_trip() {
        let im = Image::from_fn(3, 2, 5, |c, y, x| (c * 10 + y * 5 + x) as f32);
        let t = im.to_tensor();
        assert_eq!(t.size(), [3, 2, 5]);
        assert_eq!(t.double_value(&[2, 1, 3]), 28.0);
        assert_eq!(Image::from_tensor(&t.unsqueeze(0)).unwrap(), im);
    }

    #[test]
    fn non_finite_is_located() {
        let mut im = Image::new(3, 2, 2);
        assert_eq!(im.find_non_finite(), None);
        im.set(2, 1, 0, f32::NAN);
        assert_eq!(im.find_non_finite(), Some((2, 1, 0)));
    }

    #[test]
    fn resize_area_averages_footprints() {
        let im = Image::from_fn(2, 12, 9, |c, y, x| (c * 100 + y * 9 + x) as f32);
        // Integer factor: equals block averaging.
        let a = im.crop(0, 0, 12, 9).unwrap().resize_area(4, 3);
        let b = im.downsample(3);
        assert!(a.data.iter().zip(&b.data).all(|(x, y)| (x - y).abs() < 1e-4), "{a:?} {b:?}");
        // Non-integer factor: overlap-weighted means. 10 -> 4 columns: the
        // first output covers source [0, 2.5): (v0 + v1 + v2 / 2) / 2.5.
        let ramp = Image::from_fn(1, 10, 10, |_, y, x| 3.0 + x as f32 + 2.0 * y as f32);
        let r = ramp.resize_area(7, 4);
        let row0 = ramp.crop(0, 0, 1, 10).unwrap().resize_area(1, 4);
        assert!((row0.get(0, 0, 0) - (3.0 + 0.8)).abs() < 1e-5, "{row0:?}");
        // The mean is preserved for any size, and constants stay constant.
        assert!((r.mean() - ramp.mean()).abs() < 1e-4);
        let flat = Image::filled(3, 13, 11, 0.25).resize_area(5, 7);
        assert!(flat.data.iter().all(|v| (v - 0.25).abs() < 1e-6));
        assert_eq!(im.resize_area(12, 9), im);
    }

    #[test]
    fn resize_to_shrinks_by_area_and_enlarges_bilinearly() {
        let im = Image::from_fn(1, 6, 6, |_, y, x| (y * 6 + x) as f32);
        assert_eq!(im.resize_to(3, 3), im.resize_area(3, 3));
        assert_eq!(im.resize_to(9, 9), im.resize_bilinear(9, 9));
        // One side larger: bilinear (area cannot enlarge).
        assert_eq!(im.resize_to(3, 8), im.resize_bilinear(3, 8));
    }
}
