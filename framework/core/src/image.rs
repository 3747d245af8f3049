//! Typed, row-major images with a compile-time channel count (kornia-rs style).

/// A row-major image of `C` interleaved channels of `T`.
#[derive(Clone, Debug, PartialEq)]
pub struct Image<T, const C: usize> {
    width: usize,
    height: usize,
    data: Vec<T>,
}

/// 8-bit RGB colour image.
pub type Rgb8 = Image<u8, 3>;
/// 8-bit grey image.
pub type Gray8 = Image<u8, 1>;
/// Single-channel float image (intensities, confidences).
pub type GrayF32 = Image<f32, 1>;
/// Depth in metres along the optical axis (z); 0 means invalid.
pub type DepthMap = Image<f32, 1>;
/// Per-pixel flag; `true` marks the pixel (e.g. as specular, to be ignored).
pub type Mask = Image<bool, 1>;

/// The buffer length does not match `width × height × C`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("image buffer has {len} values, expected {width}×{height}×{channels} = {}", width * height * channels)]
pub struct ImageSizeError {
    /// Requested width.
    pub width: usize,
    /// Requested height.
    pub height: usize,
    /// Channels per pixel.
    pub channels: usize,
    /// Actual buffer length.
    pub len: usize,
}

impl<T: Copy + Default, const C: usize> Image<T, C> {
    /// A `width × height` image filled with `T::default()`.
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, data: vec![T::default(); width * height * C] }
    }

    /// A `width × height` image with every channel set to `value`.
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Self { width, height, data: vec![value; width * height * C] }
    }

    /// Wraps a row-major interleaved buffer.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Result<Self, ImageSizeError> {
        if data.len() != width * height * C {
            return Err(ImageSizeError { width, height, channels: C, len: data.len() });
        }
        Ok(Self { width, height, data })
    }

    /// An image whose pixel `(x, y)` is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> [T; C]) -> Self {
        let mut data = Vec::with_capacity(width * height * C);
        for y in 0..height {
            for x in 0..width {
                data.extend_from_slice(&f(x, y));
            }
        }
        Self { width, height, data }
    }

    /// [`Image::from_fn`] with rows computed in parallel (rayon); same result.
    pub fn from_fn_par(width: usize, height: usize, f: impl Fn(usize, usize) -> [T; C] + Sync) -> Self
    where
        T: Send + Sync,
    {
        use rayon::prelude::*;
        let mut data = vec![T::default(); width * height * C];
        data.par_chunks_mut((width * C).max(1)).enumerate().for_each(|(y, row)| {
            for x in 0..width {
                row[x * C..(x + 1) * C].copy_from_slice(&f(x, y));
            }
        });
        Self { width, height, data }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// `(width, height)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// The interleaved row-major buffer.
    pub fn data(&self) -> &[T] {
        &self.data
    }

    /// The interleaved row-major buffer, mutable.
    pub fn data_mut(&mut self) -> &mut [T] {
        &mut self.data
    }

    /// Consumes the image, returning its buffer.
    pub fn into_vec(self) -> Vec<T> {
        self.data
    }

    /// Whether `(x, y)` lies inside the image.
    pub fn contains(&self, x: i64, y: i64) -> bool {
        x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height
    }

    /// The channels of pixel `(x, y)`. Panics outside the image (a caller bug).
    pub fn pixel(&self, x: usize, y: usize) -> [T; C] {
        let i = (y * self.width + x) * C;
        let mut out = [T::default(); C];
        out.copy_from_slice(&self.data[i..i + C]);
        out
    }

    /// Sets pixel `(x, y)`. Panics outside the image (a caller bug).
    pub fn set_pixel(&mut self, x: usize, y: usize, value: [T; C]) {
        let i = (y * self.width + x) * C;
        self.data[i..i + C].copy_from_slice(&value);
    }

    /// Rows of interleaved values, for row-parallel processing.
    pub fn rows(&self) -> std::slice::ChunksExact<'_, T> {
        self.data.chunks_exact((self.width * C).max(1))
    }

    /// Mutable rows of interleaved values.
    pub fn rows_mut(&mut self) -> std::slice::ChunksExactMut<'_, T> {
        self.data.chunks_exact_mut((self.width * C).max(1))
    }
}

impl<T: Copy + Default> Image<T, 1> {
    /// The value at `(x, y)`. Panics outside the image (a caller bug).
    pub fn at(&self, x: usize, y: usize) -> T {
        self.data[y * self.width + x]
    }

    /// Mutable reference to the value at `(x, y)`.
    pub fn at_mut(&mut self, x: usize, y: usize) -> &mut T {
        &mut self.data[y * self.width + x]
    }
}

/// The NTSC luminance weights of r, g, b (the paper's Sec. 3.3).
pub const NTSC_WEIGHTS: [f64; 3] = [0.2989, 0.5870, 0.1140];

/// NTSC luminance of a linear RGB triple (an albedo, a linear radiance).
pub fn luminance(rgb: [f64; 3]) -> f64 {
    NTSC_WEIGHTS.iter().zip(rgb).map(|(w, v)| w * v).sum()
}

/// Luminance of an RGB pixel with the NTSC weights the paper uses (Sec. 3.3:
/// I = 0.2989 r + 0.5870 g + 0.1140 b), in the pixel's own units.
pub fn intensity_ntsc(rgb: [u8; 3]) -> f32 {
    0.2989 * f32::from(rgb[0]) + 0.5870 * f32::from(rgb[1]) + 0.1140 * f32::from(rgb[2])
}

/// The NTSC intensity image of a colour image, in [0, 255] (pixels in parallel).
pub fn gray_from_rgb(src: &Rgb8) -> GrayF32 {
    use rayon::prelude::*;
    let data = src.data().par_chunks_exact(3).map(|p| intensity_ntsc([p[0], p[1], p[2]])).collect();
    Image { width: src.width(), height: src.height(), data }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn from_vec_checks_size() {
        assert!(Rgb8::from_vec(2, 2, vec![0; 12]).is_ok());
        let err = Rgb8::from_vec(2, 2, vec![0; 11]).unwrap_err();
        assert_eq!(err.len, 11);
        assert!(err.to_string().contains("2×2×3 = 12"));
    }

    #[test]
    fn pixel_roundtrip_and_layout() {
        let mut img = Rgb8::new(3, 2);
        img.set_pixel(2, 1, [1, 2, 3]);
        assert_eq!(img.pixel(2, 1), [1, 2, 3]);
        assert_eq!(&img.data()[15..18], &[1, 2, 3]);
        assert_eq!(img.rows().count(), 2);
    }

    #[test]
    fn parallel_construction_equals_sequential() {
        let f = |x: usize, y: usize| [(x * 7 + y * 3) as u16, (x ^ y) as u16];
        assert_eq!(Image::<u16, 2>::from_fn(37, 23, f), Image::<u16, 2>::from_fn_par(37, 23, f));
        assert_eq!(Image::<u16, 2>::from_fn_par(0, 5, f).data().len(), 0);
    }

    #[test]
    fn ntsc_weights_sum_to_one() {
        assert!((intensity_ntsc([255, 255, 255]) - 255.0).abs() < 0.05);
        assert!((intensity_ntsc([255, 0, 0]) - 0.2989 * 255.0).abs() < 1e-3);
    }
}
