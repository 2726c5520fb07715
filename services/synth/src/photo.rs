//! Photographs as textures: a grey image with its mip-map pyramid (Williams, "Pyramidal
//! Parametrics", SIGGRAPH 1983), sampled trilinearly at the pixel's footprint so that a
//! picture seen from far away neither aliases nor flickers, as the procedural textures
//! fade their fine octaves (texture.rs). Decoding is the caller's (no I/O here): the synth
//! command decodes the JPEGs shipped in `services/synth/photos/`.

/// Why a photograph was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PhotoError {
    /// Width or height is zero.
    #[error("a photograph needs at least one pixel, got {width} x {height}")]
    Empty { width: usize, height: usize },
    /// The pixel buffer does not hold width x height values.
    #[error("{width} x {height} photograph with {len} pixel values")]
    WrongSize {
        width: usize,
        height: usize,
        len: usize,
    },
}

/// One level of the pyramid, brightness in [0, 1], row-major.
#[derive(Debug, Clone, PartialEq)]
struct Level {
    width: usize,
    height: usize,
    values: Vec<f32>,
}

impl Level {
    /// Bilinear lookup at texture coordinates (s, t) in [0, 1], edges clamped.
    fn bilinear(&self, s: f64, t: f64) -> f64 {
        let x = (s * self.width as f64 - 0.5).clamp(0.0, (self.width - 1) as f64);
        let y = (t * self.height as f64 - 0.5).clamp(0.0, (self.height - 1) as f64);
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let at = |x: usize, y: usize| f64::from(self.values[y * self.width + x]);
        let top = at(x0, y0) + (at(x1, y0) - at(x0, y0)) * fx;
        let bottom = at(x0, y1) + (at(x1, y1) - at(x0, y1)) * fx;
        top + (bottom - top) * fy
    }

    /// The next level: 2 x 2 box filter (an odd last row or column is averaged in).
    fn halved(&self) -> Self {
        let (width, height) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut values = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                let (mut sum, mut n) = (0.0f32, 0.0f32);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (sx, sy) = (2 * x + dx, 2 * y + dy);
                    if sx < self.width && sy < self.height {
                        sum += self.values[sy * self.width + sx];
                        n += 1.0;
                    }
                }
                values.push(sum / n);
            }
        }
        Self {
            width,
            height,
            values,
        }
    }
}

/// A grey photograph and its pyramid, down to a single pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct Photo {
    levels: Vec<Level>,
}

impl Photo {
    /// From 8-bit grey pixels, row-major.
    pub fn from_grey(width: usize, height: usize, pixels: &[u8]) -> Result<Self, PhotoError> {
        if width == 0 || height == 0 {
            return Err(PhotoError::Empty { width, height });
        }
        if pixels.len() != width * height {
            return Err(PhotoError::WrongSize {
                width,
                height,
                len: pixels.len(),
            });
        }
        let mut levels = vec![Level {
            width,
            height,
            values: pixels.iter().map(|&p| f32::from(p) / 255.0).collect(),
        }];
        while let Some(last) = levels.last().filter(|l| l.width > 1 || l.height > 1) {
            let next = last.halved();
            levels.push(next);
        }
        Ok(Self { levels })
    }

    /// Width of the full-resolution image, pixels.
    pub fn width(&self) -> usize {
        self.levels[0].width
    }

    /// Height of the full-resolution image, pixels.
    pub fn height(&self) -> usize {
        self.levels[0].height
    }

    /// Brightness in [0, 1] at (s, t) in [0, 1] x [0, 1] (s along the width, t down the
    /// height), for a screen pixel covering `footprint` photo pixels: trilinear between the
    /// two pyramid levels whose texels are nearest that size.
    pub fn sample(&self, s: f64, t: f64, footprint: f64) -> f64 {
        let lod = footprint
            .max(1.0)
            .log2()
            .min((self.levels.len() - 1) as f64);
        let fine = lod.floor() as usize;
        let coarse = (fine + 1).min(self.levels.len() - 1);
        let a = self.levels[fine].bilinear(s, t);
        let b = self.levels[coarse].bilinear(s, t);
        a + (b - a) * (lod - fine as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 64 x 48 checkerboard of 2-pixel squares, black and white.
    fn checkerboard() -> Photo {
        let (w, h) = (64, 48);
        let pixels: Vec<u8> = (0..w * h)
            .map(|i| {
                if ((i % w) / 2 + (i / w) / 2) % 2 == 0 {
                    0
                } else {
                    255
                }
            })
            .collect();
        Photo::from_grey(w, h, &pixels).expect("photo")
    }

    #[test]
    fn close_up_shows_the_pixels_and_far_away_their_mean() {
        let p = checkerboard();
        assert_eq!((p.width(), p.height()), (64, 48));
        // At one photo pixel per screen pixel the squares are resolved...
        let dark = p.sample(0.5 / 64.0, 0.5 / 48.0, 1.0);
        let light = p.sample(2.5 / 64.0, 0.5 / 48.0, 1.0);
        assert!(dark < 0.01 && light > 0.99, "{dark} {light}");
        // ...and a screen pixel covering 8 of them sees the mean, not an aliased square.
        for k in 0..20 {
            let (s, t) = (0.013 + 0.047 * k as f64, 0.021 + 0.043 * k as f64);
            let v = p.sample(s % 1.0, t % 1.0, 8.0);
            assert!((v - 0.5).abs() < 0.05, "{v} at {s} {t}");
        }
        // The pyramid ends in one pixel.
        assert!((p.sample(0.3, 0.7, 1e6) - 0.5).abs() < 1e-6);
    }

    #[test]
    fn bad_sizes_are_refused() {
        assert_eq!(
            Photo::from_grey(0, 4, &[]),
            Err(PhotoError::Empty {
                width: 0,
                height: 4
            })
        );
        assert_eq!(
            Photo::from_grey(2, 2, &[1, 2, 3]),
            Err(PhotoError::WrongSize {
                width: 2,
                height: 2,
                len: 3
            })
        );
    }
}
