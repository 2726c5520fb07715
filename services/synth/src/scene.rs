//! Scenes: textured rectangles in a world frame with the camera convention (x right,
//! y down, z forward; gravity +y, the eye at y = 0 and the floor at y = +1.6 m).

use crate::photo::Photo;
use crate::texture::Texture;
use nalgebra::Vector3;
use std::sync::Arc;

/// A photograph hung on a plane: it covers the rectangle `[u0, u0 + width] x [v0, v0 +
/// height]` of the plane's coordinates (metres), the photo's top row at `v0`.
#[derive(Debug, Clone, PartialEq)]
pub struct Picture {
    pub photo: Arc<Photo>,
    pub u0: f64,
    pub v0: f64,
    pub width: f64,
    pub height: f64,
}

impl Picture {
    /// How much of the picture a pixel at (u, v) with `footprint` metres sees, in [0, 1]
    /// (its edges softened over one footprint, as the posters' are), and the picture's
    /// brightness there; `None` when the pixel is off the picture.
    pub fn sample(&self, u: f64, v: f64, footprint: f64) -> Option<(f64, f64)> {
        let rect = [self.u0, self.v0, self.width, self.height];
        let coverage = crate::texture::soft_coverage(u, v, rect, footprint.max(1e-9));
        if coverage <= 0.0 {
            return None;
        }
        let (s, t) = ((u - self.u0) / self.width, (v - self.v0) / self.height);
        let texels = footprint * self.photo.width() as f64 / self.width;
        Some((coverage, self.photo.sample(s, t, texels)))
    }
}

/// A textured rectangle: `origin + a u_axis + b v_axis` for a in [0, width], b in [0, height].
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    pub origin: Vector3<f64>,
    pub u_axis: Vector3<f64>,
    pub v_axis: Vector3<f64>,
    pub width: f64,
    pub height: f64,
    pub texture: Texture,
    /// Photographs hung on it, drawn over the texture.
    pub pictures: Vec<Picture>,
    pub(crate) normal: Vector3<f64>,
}

/// Where a ray meets a plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray.
    pub distance: f64,
    pub u: f64,
    pub v: f64,
    /// |cos| of the angle between the ray and the plane normal.
    pub cos_incidence: f64,
}

impl Plane {
    /// A rectangle spanned by two orthogonal edge vectors from `origin` (their lengths are
    /// the sides).
    pub fn new(
        origin: Vector3<f64>,
        u_edge: Vector3<f64>,
        v_edge: Vector3<f64>,
        texture: Texture,
    ) -> Self {
        let (width, height) = (u_edge.norm(), v_edge.norm());
        let (u_axis, v_axis) = (u_edge / width, v_edge / height);
        Self {
            origin,
            u_axis,
            v_axis,
            width,
            height,
            texture,
            pictures: Vec::new(),
            normal: u_axis.cross(&v_axis).normalize(),
        }
    }

    /// Distance from `p` to the nearest point of the rectangle.
    pub fn distance_to(&self, p: &Vector3<f64>) -> f64 {
        let d = p - self.origin;
        let a = d.dot(&self.u_axis).clamp(0.0, self.width);
        let b = d.dot(&self.v_axis).clamp(0.0, self.height);
        (p - (self.origin + self.u_axis * a + self.v_axis * b)).norm()
    }

    /// The nearest intersection of the ray `o + t d` (d unit, t > 1 cm) with the rectangle.
    pub fn intersect(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<Hit> {
        let denom = self.normal.dot(d);
        if denom.abs() < 1e-9 {
            return None;
        }
        let t = self.normal.dot(&(self.origin - o)) / denom;
        if t <= 0.01 {
            return None;
        }
        let rel = o + d * t - self.origin;
        let (u, v) = (rel.dot(&self.u_axis), rel.dot(&self.v_axis));
        (u >= 0.0 && u <= self.width && v >= 0.0 && v <= self.height).then_some(Hit {
            distance: t,
            u,
            v,
            cos_incidence: denom.abs(),
        })
    }
}

/// A set of planes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scene {
    pub planes: Vec<Plane>,
}

impl Scene {
    /// Distance from `p` to the nearest surface.
    pub fn clearance(&self, p: &Vector3<f64>) -> f64 {
        self.planes
            .iter()
            .map(|plane| plane.distance_to(p))
            .fold(f64::INFINITY, f64::min)
    }

    /// The nearest hit over all planes, with its plane.
    pub fn cast(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(Hit, &Plane)> {
        Self::nearest(self.planes.iter(), o, d)
    }

    /// The nearest hit over `planes`.
    pub fn nearest<'a>(
        planes: impl Iterator<Item = &'a Plane>,
        o: &Vector3<f64>,
        d: &Vector3<f64>,
    ) -> Option<(Hit, &'a Plane)> {
        planes
            .filter_map(|p| p.intersect(o, d).map(|h| (h, p)))
            .min_by(|a, b| a.0.distance.total_cmp(&b.0.distance))
    }

    /// The planes that can be seen at all from `position` looking along `forward` with a
    /// field of view under 180 deg: those with a corner in front of the camera. A cheap
    /// per-frame cull that halves the work in a room.
    pub fn facing(&self, position: &Vector3<f64>, forward: &Vector3<f64>) -> Vec<&Plane> {
        self.planes
            .iter()
            .filter(|p| {
                let corners = [
                    p.origin,
                    p.origin + p.u_axis * p.width,
                    p.origin + p.v_axis * p.height,
                    p.origin + p.u_axis * p.width + p.v_axis * p.height,
                ];
                corners.iter().any(|c| (c - position).dot(forward) > 0.0)
            })
            .collect()
    }

    fn texture(seed: u64, index: u64, scale_m: f64) -> Texture {
        let s = seed.wrapping_mul(1000).wrapping_add(index);
        Texture {
            seed: s,
            scale_m,
            base: 0.35 + 0.3 * ((s.wrapping_mul(2654435761) % 1000) as f64 / 1000.0),
        }
    }

    /// An axis-aligned box standing on the floor (y = 1.6): its four sides and top.
    fn add_box(&mut self, seed: u64, centre_x: f64, centre_z: f64, side: f64, height: f64) {
        let n = self.planes.len() as u64;
        let (x0, x1) = (centre_x - side / 2.0, centre_x + side / 2.0);
        let (z0, z1) = (centre_z - side / 2.0, centre_z + side / 2.0);
        let top = 1.6 - height;
        let up = Vector3::new(0.0, height, 0.0);
        let faces = [
            (Vector3::new(x0, top, z0), Vector3::new(side, 0.0, 0.0)),
            (Vector3::new(x1, top, z0), Vector3::new(0.0, 0.0, side)),
            (Vector3::new(x1, top, z1), Vector3::new(-side, 0.0, 0.0)),
            (Vector3::new(x0, top, z1), Vector3::new(0.0, 0.0, -side)),
        ];
        for (i, (origin, edge)) in faces.into_iter().enumerate() {
            self.planes.push(Plane::new(
                origin,
                edge,
                up,
                Self::texture(seed, n + i as u64, 0.4),
            ));
        }
        self.planes.push(Plane::new(
            Vector3::new(x0, top, z0),
            Vector3::new(side, 0.0, 0.0),
            Vector3::new(0.0, 0.0, side),
            Self::texture(seed, n + 4, 0.4),
        ));
    }

    /// The paper's scene (section "Egocentric Videos"): planes of 1.28, 2.56 and 5.12 m at
    /// 3.5, 5 and 8 m, in front of a 20 x 12 m background wall at 12 m, and a floor.
    pub fn paper_planes(seed: u64) -> Self {
        let mut s = Scene::default();
        let down = |h: f64| Vector3::new(0.0, h, 0.0);
        let right = |w: f64| Vector3::new(w, 0.0, 0.0);
        for (i, (x, y, z, side)) in [
            (0.3, -0.9, 3.5, 1.28),
            (-2.3, -1.6, 5.0, 2.56),
            (-1.5, -2.56, 8.0, 5.12),
        ]
        .into_iter()
        .enumerate()
        {
            s.planes.push(Plane::new(
                Vector3::new(x, y, z),
                right(side),
                down(side),
                Self::texture(seed, i as u64, 0.3 * side / 1.28),
            ));
        }
        s.planes.push(Plane::new(
            Vector3::new(-10.0, -6.0, 12.0),
            right(20.0),
            down(12.0),
            Self::texture(seed, 3, 1.0),
        ));
        s.planes.push(Plane::new(
            Vector3::new(-10.0, 1.6, -2.0),
            right(20.0),
            Vector3::new(0.0, 0.0, 14.0),
            Self::texture(seed, 4, 0.5),
        ));
        s
    }

    /// A 16 x 16 x 3 m room: textured floor, ceiling and walls, a 4 x 4 m central block
    /// the walker circles, and boxes along the way.
    pub fn room(seed: u64) -> Self {
        let mut s = Scene::default();
        let h = 3.0;
        let top = 1.6 - h;
        let walls = [
            (Vector3::new(-8.0, top, 8.0), Vector3::new(16.0, 0.0, 0.0)),
            (Vector3::new(8.0, top, 8.0), Vector3::new(0.0, 0.0, -16.0)),
            (Vector3::new(8.0, top, -8.0), Vector3::new(-16.0, 0.0, 0.0)),
            (Vector3::new(-8.0, top, -8.0), Vector3::new(0.0, 0.0, 16.0)),
        ];
        for (i, (origin, edge)) in walls.into_iter().enumerate() {
            s.planes.push(Plane::new(
                origin,
                edge,
                Vector3::new(0.0, h, 0.0),
                Self::texture(seed, i as u64, 0.6),
            ));
        }
        for (i, y) in [1.6, top].into_iter().enumerate() {
            s.planes.push(Plane::new(
                Vector3::new(-8.0, y, -8.0),
                Vector3::new(16.0, 0.0, 0.0),
                Vector3::new(0.0, 0.0, 16.0),
                Self::texture(seed, 10 + i as u64, 0.5),
            ));
        }
        s.add_box(seed, 0.0, 0.0, 4.0, h);
        for (x, z, side, height) in [
            (6.5, 3.0, 1.0, 1.0),
            (-6.5, -2.0, 1.2, 1.6),
            (3.0, -6.6, 0.8, 0.8),
            (-2.5, 6.6, 1.0, 1.2),
        ] {
            s.add_box(seed, x, z, side, height);
        }
        s
    }
}

impl Scene {
    /// A wall from `a` to `b` (on the floor, y = 1.6) rising `height` m, textured with
    /// feature size `scale_m`; its front is either side (planes are two-sided).
    fn add_wall(&mut self, seed: u64, a: (f64, f64), b: (f64, f64), height: f64, scale_m: f64) {
        let n = self.planes.len() as u64;
        self.planes.push(Plane::new(
            Vector3::new(a.0, 1.6 - height, a.1),
            Vector3::new(b.0 - a.0, 0.0, b.1 - a.1),
            Vector3::new(0.0, height, 0.0),
            Self::texture(seed, n, scale_m),
        ));
    }

    /// Hangs `photos` in turn on the last plane added (a wall): pictures `size` m wide and
    /// high whose tops are `top` m below the wall's top, one every `spacing` m from
    /// `spacing / 2` along it.
    fn hang_pictures(&mut self, photos: &[Arc<Photo>], size: (f64, f64), top: f64, spacing: f64) {
        let Some(wall) = self.planes.last_mut() else {
            return;
        };
        let mut u0 = spacing / 2.0 - size.0 / 2.0;
        let mut next = wall.texture.seed as usize;
        while !photos.is_empty() && u0 + size.0 <= wall.width {
            wall.pictures.push(Picture {
                photo: photos[next % photos.len()].clone(),
                u0,
                v0: top,
                width: size.0,
                height: size.1,
            });
            next += 1;
            u0 += spacing;
        }
    }

    /// A horizontal square of side `2 half` centred on the vertical axis at height `y`.
    fn add_slab(&mut self, seed: u64, half: f64, y: f64, scale_m: f64) {
        let n = self.planes.len() as u64;
        self.planes.push(Plane::new(
            Vector3::new(-half, y, -half),
            Vector3::new(2.0 * half, 0.0, 0.0),
            Vector3::new(0.0, 0.0, 2.0 * half),
            Self::texture(seed, n, scale_m),
        ));
    }

    /// An indoor corridor: a 2.2 m wide, 2.6 m high ring around an 8 x 8 m core, the
    /// walker's 10 m loop in it 1 m from the core and 1.2 m from the outer wall, with a
    /// cabinet in each side's middle. Near walls on both sides and a ceiling: large,
    /// fast flow during head scans, and the far end of each straight 12 m away.
    /// `photos` are hung as 1.2 x 0.9 m pictures at eye level along the outer walls, one
    /// every 3 m (none when empty).
    pub fn corridor(seed: u64, photos: &[Arc<Photo>]) -> Self {
        let mut s = Scene::default();
        let (h, outer) = (2.6, 6.2);
        s.add_box(seed, 0.0, 0.0, 8.0, h);
        let corners = [
            (-outer, -outer),
            (outer, -outer),
            (outer, outer),
            (-outer, outer),
        ];
        for k in 0..4 {
            s.add_wall(seed, corners[k], corners[(k + 1) % 4], h, 0.5);
            s.hang_pictures(photos, (1.2, 0.9), 0.55, 3.0);
        }
        s.add_slab(seed, outer, 1.6, 0.4);
        s.add_slab(seed, outer, 1.6 - h, 0.5);
        for (x, z) in [(0.0, -5.9), (5.9, 0.0), (0.0, 5.9), (-5.9, 0.0)] {
            s.add_box(seed, x, z, 0.6, 1.0);
        }
        s
    }

    /// An outdoor street: the walker's 10 m loop on the pavement 1 m around a 12 m high
    /// 8 x 8 m block, facades of 8-16 m across the 7 m street, lamp posts, parked cars as
    /// boxes, ground, and open sky above (nothing hit: flat grey, no corners). Depths from
    /// 1 m to beyond 30 m down each street.
    /// `photos` are hung as 4 x 3 m billboards 2 m above the pavement on the facades across,
    /// one every 10 m (none when empty).
    pub fn street(seed: u64, photos: &[Arc<Photo>]) -> Self {
        let mut s = Scene::default();
        s.add_box(seed, 0.0, 0.0, 8.0, 12.0);
        let far = 12.0;
        let heights = [9.0, 16.0, 12.0, 8.0, 14.0, 11.0, 10.0, 15.0];
        // Each side of the street across: two facades of 20 m, of different heights.
        let corners = [(-far, -far), (far, -far), (far, far), (-far, far)];
        for k in 0..4 {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            let mid = ((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0);
            s.add_wall(seed, a, mid, heights[2 * k], 1.0);
            s.hang_pictures(photos, (4.0, 3.0), heights[2 * k] - 5.0, 10.0);
            s.add_wall(seed, mid, b, heights[2 * k + 1], 1.0);
            s.hang_pictures(photos, (4.0, 3.0), heights[2 * k + 1] - 5.0, 10.0);
        }
        s.add_slab(seed, far + 8.0, 1.6, 0.6);
        for (x, z) in [(-6.0, -2.0), (6.0, 2.5), (2.0, 6.0), (-2.5, -6.0)] {
            s.add_box(seed, x, z, 0.2, 5.0); // lamp posts, 1 m from the path
        }
        for (x, z) in [(8.5, -3.0), (-8.5, 4.0), (3.5, 8.5), (-4.0, -8.5)] {
            s.add_box(seed, x, z, 1.8, 1.5); // parked cars
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pictures_cover_their_rectangle_with_soft_edges() {
        // A 2 x 2 photo: left column black, right column white, on a 1.2 x 0.9 m picture.
        let photo = Arc::new(Photo::from_grey(2, 2, &[0, 255, 0, 255]).expect("photo"));
        let picture = Picture {
            photo: photo.clone(),
            u0: 1.0,
            v0: 0.5,
            width: 1.2,
            height: 0.9,
        };
        let fine = 0.001; // 1 mm per pixel: well resolved
        let (c, left) = picture.sample(1.05, 0.95, fine).expect("on it");
        assert!((c - 1.0).abs() < 1e-12 && left < 1e-6, "{c} {left}");
        let (_, right) = picture.sample(2.15, 0.95, fine).expect("on it");
        assert!(right > 1.0 - 1e-6, "{right}");
        let (edge, _) = picture.sample(1.0, 0.95, fine).expect("edge");
        assert!(
            (edge - 0.5).abs() < 1e-9,
            "half covered at the edge: {edge}"
        );
        assert!(picture.sample(0.9, 0.95, fine).is_none());
        assert!(picture.sample(1.5, 1.5, fine).is_none());
        // Hung along every outer corridor wall, alternating photographs, within the wall.
        let corridor = Scene::corridor(1, &[photo.clone(), photo]);
        let hung: Vec<&Picture> = corridor.planes.iter().flat_map(|p| &p.pictures).collect();
        assert_eq!(
            hung.len(),
            16,
            "four 3 m spaced pictures on each 12.4 m wall"
        );
        for p in corridor.planes.iter().filter(|p| !p.pictures.is_empty()) {
            for q in &p.pictures {
                assert!(q.u0 >= 0.0 && q.u0 + q.width <= p.width && q.v0 + q.height <= p.height);
            }
        }
    }

    #[test]
    fn the_walker_loop_fits_the_corridor_and_the_street() {
        // The loop's corners and side midpoints (half side 5 m) keep clear of every surface,
        // and the corridor is closed while the street is open to the sky.
        let points: Vec<Vector3<f64>> = [
            (-5.0, -5.0),
            (0.0, -5.0),
            (5.0, 0.0),
            (5.0, 5.0),
            (-5.0, 0.0),
        ]
        .into_iter()
        .map(|(x, z)| Vector3::new(x, 0.0, z))
        .collect();
        for (scene, least) in [(Scene::corridor(1, &[]), 0.6), (Scene::street(1, &[]), 0.5)] {
            for p in &points {
                assert!(scene.clearance(p) >= least, "{p:?}: {}", scene.clearance(p));
            }
        }
        let up = -Vector3::y();
        assert!(
            Scene::corridor(1, &[]).cast(&points[1], &up).is_some(),
            "ceiling"
        );
        assert!(Scene::street(1, &[]).cast(&points[1], &up).is_none(), "sky");
        // Looking down the street from a loop corner, the facades across are ~7 m away.
        let (hit, _) = Scene::street(1, &[])
            .cast(&points[0], &Vector3::new(0.0, 0.0, -1.0))
            .expect("facade");
        assert!((hit.distance - 7.0).abs() < 1e-9, "{hit:?}");
    }

    #[test]
    fn rays_hit_the_nearest_plane() {
        let s = Scene::paper_planes(1);
        let o = Vector3::zeros();
        // Straight ahead the 2.56 m plane (5 m) hides the 5.12 m one (8 m).
        let (hit, _) = s
            .cast(&o, &Vector3::new(0.0, 0.0, 1.0))
            .expect("straight ahead");
        assert!((hit.distance - 5.0).abs() < 1e-9, "{hit:?}");
        let ray = Vector3::new(0.35, -0.3, 1.0);
        let (hit, _) = s.cast(&o, &ray.normalize()).expect("up right");
        assert!((hit.distance / ray.norm() - 8.0).abs() < 1e-6, "{hit:?}");
        let (hit, _) = s
            .cast(&o, &Vector3::new(0.3, -0.5, 3.5).normalize())
            .expect("near plane");
        assert!(hit.distance < 4.0);
        let room = Scene::room(1);
        let inside = Vector3::new(5.0, 0.0, 5.0);
        for d in [
            Vector3::x(),
            -Vector3::x(),
            Vector3::z(),
            -Vector3::z(),
            Vector3::y(),
            -Vector3::y(),
        ] {
            assert!(
                room.cast(&inside, &d).is_some(),
                "the room is closed: {d:?}"
            );
        }
    }
}
