//! Procedural, band-limited plane textures: value noise over several octaves plus
//! "posters" (random grey rectangles with soft edges) that give the tracker corners at
//! every distance. Band-limited analytically: octaves and edges finer than the pixel's
//! footprint on the plane fade out, so distant surfaces do not alias or flicker (what a
//! mip-mapped photograph would do), and frames stay deterministic for a seed.

/// A 2-D integer hash (a few rounds of multiply-xorshift): the lattice values of the noise.
fn hash(x: i64, y: i64, seed: u64) -> f64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 31;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// `x.floor()` without the library call it compiles to on baseline x86-64 (no SSE4.1
/// `roundsd`), which was a tenth of the renderer's time; exact for |x| < 2^63, which
/// texture coordinates in lattice units always are.
pub(crate) fn fast_floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// Lattice values a pixel's neighbours reuse: a texture is sampled pixel after pixel along
/// a row, and consecutive pixels mostly fall in the same lattice cell of every coarse
/// octave and in the same poster cell, so their hashes are kept instead of recomputed
/// (the same values, so the same image). One per rendering thread.
#[derive(Debug, Default, Clone)]
pub struct SampleCache {
    octaves: [Option<CachedCell<4>>; 5],
    poster: Option<CachedCell<6>>,
}

/// The hash values of one lattice cell, keyed by (seed, x, y).
#[derive(Debug, Clone, Copy)]
struct CachedCell<const N: usize> {
    key: (u64, i64, i64),
    values: [f64; N],
}

impl<const N: usize> CachedCell<N> {
    /// The values of cell `key` from `slot`, computed by `make` (and kept) if it holds
    /// another cell. Inlined: called per octave per pixel, the call was 7 % of rendering.
    #[inline(always)]
    fn get(
        slot: &mut Option<Self>,
        key: (u64, i64, i64),
        make: impl FnOnce() -> [f64; N],
    ) -> [f64; N] {
        match slot {
            Some(cell) if cell.key == key => cell.values,
            _ => {
                let values = make();
                *slot = Some(Self { key, values });
                values
            }
        }
    }
}

/// Value noise in [0, 1] at (u, v) in lattice units; `slot` keeps the last cell's corners.
#[inline(always)]
fn value_noise(u: f64, v: f64, seed: u64, slot: &mut Option<CachedCell<4>>) -> f64 {
    let (x0, y0) = (fast_floor(u), fast_floor(v));
    let (fx, fy) = (smooth(u - x0), smooth(v - y0));
    let (x, y) = (x0 as i64, y0 as i64);
    let [a, b, c, d] = CachedCell::get(slot, (seed, x, y), || {
        [
            hash(x, y, seed),
            hash(x + 1, y, seed),
            hash(x, y + 1, seed),
            hash(x + 1, y + 1, seed),
        ]
    });
    let top = a + (b - a) * fx;
    let bottom = c + (d - c) * fx;
    top + (bottom - top) * fy
}

/// How much of a rectangle `[u0, u0 + width] x [v0, v0 + height]` a pixel at (u, v) covers,
/// in [0, 1], its edges softened over `soft` (the pixel's footprint, same units): the
/// posters' and the photographs' edges, band-limited alike.
pub(crate) fn soft_coverage(u: f64, v: f64, rect: [f64; 4], soft: f64) -> f64 {
    soft_coverage_scaled(u, v, rect, 1.0 / soft)
}

/// [`soft_coverage`] with the reciprocal of `soft` given: multiplied instead of divided by.
#[inline(always)]
fn soft_coverage_scaled(u: f64, v: f64, rect: [f64; 4], per_soft: f64) -> f64 {
    let [u0, v0, width, height] = rect;
    let inside_u = ((u - u0).min(u0 + width - u) * per_soft).clamp(-0.5, 0.5) + 0.5;
    let inside_v = ((v - v0).min(v0 + height - v) * per_soft).clamp(-0.5, 0.5) + 0.5;
    inside_u * inside_v
}

/// How much of a feature survives, from the ratio `r` of its wavelength to twice the
/// pixel's footprint on the plane: 1 when it spans many pixels, 0 below two pixels
/// (Nyquist), linear in between.
fn keep_ratio(r: f64) -> f64 {
    (r - 1.0).clamp(0.0, 1.0)
}

/// A plane's texture: seed and feature size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Texture {
    pub seed: u64,
    /// Wavelength of the coarsest noise octave and side of a poster cell, metres.
    pub scale_m: f64,
    /// Mean brightness in [0, 1] (planes differ, so edges between them are visible).
    pub base: f64,
}

impl Texture {
    /// Brightness in [0, 1] at plane coordinates (u, v) metres, seen with `footprint`
    /// metres per pixel.
    pub fn sample(&self, u: f64, v: f64, footprint: f64) -> f64 {
        self.sample_cached(u, v, footprint, &mut SampleCache::default())
    }

    /// [`Texture::sample`] with the lattice values of the previous sample at hand.
    ///
    /// Two divisions per sample (the lattice scale's and the footprint's reciprocals)
    /// where the formulas below read seven: called once per pixel, they were most of its
    /// cost. Products by a reciprocal round differently from the quotients in the last
    /// place only; every function of them here is continuous, so the grey levels are the
    /// same (the render bench's checksum).
    pub fn sample_cached(&self, u: f64, v: f64, footprint: f64, cache: &mut SampleCache) -> f64 {
        // Noise: 5 octaves, each half the wavelength and amplitude of the previous.
        // Octave k's wavelength is scale_m / 2^k, so its lattice coordinates are u / scale_m
        // times 2^k and its `keep` ratio (wavelength over twice the footprint) the
        // coarsest one's over 2^k: scaling by a power of two is exact.
        let per_metre = 1.0 / self.scale_m;
        let per_footprint = 1.0 / footprint.max(1e-9);
        let (lu, lv) = (u * per_metre, v * per_metre);
        let coarsest_ratio = 0.5 * self.scale_m * per_footprint;
        let mut ratio = coarsest_ratio;
        let mut sum = 0.0;
        let (mut lattice, mut amplitude) = (1.0, 0.5);
        for (octave, slot) in cache.octaves.iter_mut().enumerate() {
            let k = keep_ratio(ratio);
            if k > 0.0 {
                let n = value_noise(
                    lu * lattice,
                    lv * lattice,
                    self.seed.wrapping_add(octave as u64),
                    slot,
                );
                sum += amplitude * (k * n + (1.0 - k) * 0.5);
            } else {
                sum += amplitude * 0.5; // unresolved: its mean, without computing it
            }
            ratio *= 0.5;
            lattice *= 2.0;
            amplitude *= 0.5;
        }
        // The amplitudes sum to 31/32.
        let noise = sum * (32.0 / 31.0);
        // Posters: in each cell of the poster lattice (the coarsest octave's), with
        // probability 0.6, a rectangle of random size and grey level, edges softened over
        // one footprint.
        let (cx, cy) = (fast_floor(lu), fast_floor(lv));
        let (ix, iy) = (cx as i64, cy as i64);
        let salt = self.seed.wrapping_mul(31).wrapping_add(7);
        let mut value = self.base + 0.45 * (noise - 0.5);
        let poster = CachedCell::get(&mut cache.poster, (salt, ix, iy), || {
            std::array::from_fn(|k| hash(ix, iy, salt + k as u64))
        });
        if poster[0] < 0.6 {
            let w = 0.25 + 0.5 * poster[1];
            let h = 0.25 + 0.5 * poster[2];
            let x0 = cx + (1.0 - w) * poster[3];
            let y0 = cy + (1.0 - h) * poster[4];
            // Cells per footprint, and its inverse (`soft_coverage`'s edge softening).
            let per_soft = (self.scale_m * per_footprint).min(1e6);
            let coverage = soft_coverage_scaled(lu, lv, [x0, y0, w, h], per_soft);
            // Posters too small to resolve fade to their mean.
            let k = keep_ratio(w.min(h) * coarsest_ratio);
            let grey = 0.1 + 0.8 * poster[5];
            value = value * (1.0 - k * coverage) + k * coverage * grey;
        }
        value.clamp(0.0, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_bounded_and_band_limited() {
        let t = Texture {
            seed: 3,
            scale_m: 0.5,
            base: 0.5,
        };
        let mut near_var = 0.0;
        let mut far_var = 0.0;
        let n = 400;
        let (mut near_mean, mut far_mean) = (0.0, 0.0);
        let samples: Vec<(f64, f64)> = (0..n)
            .map(|i| (0.0137 * i as f64, 0.0291 * i as f64))
            .collect();
        for &(u, v) in &samples {
            let a = t.sample(u, v, 0.002);
            assert_eq!(a, t.sample(u, v, 0.002), "deterministic");
            assert!((0.0..=1.0).contains(&a));
            near_mean += a / n as f64;
            far_mean += t.sample(u, v, 5.0) / n as f64;
        }
        for &(u, v) in &samples {
            near_var += (t.sample(u, v, 0.002) - near_mean).powi(2) / n as f64;
            far_var += (t.sample(u, v, 5.0) - far_mean).powi(2) / n as f64;
        }
        // Close up the texture has contrast; seen from far away (a footprint of 5 m per
        // pixel) every feature is below Nyquist and it is nearly flat: no aliasing.
        assert!(near_var.sqrt() > 0.1, "near contrast {}", near_var.sqrt());
        assert!(far_var.sqrt() < 0.02, "far contrast {}", far_var.sqrt());
    }
}
