//! Scenes: textured rectangles in a world frame with the camera convention (x right,
//! y down, z forward; gravity +y, the eye at y = 0 and the floor at y = +1.6 m).

use crate::texture::Texture;
use nalgebra::Vector3;

/// A textured rectangle: `origin + a u_axis + b v_axis` for a in [0, width], b in [0, height].
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    pub origin: Vector3<f64>,
    pub u_axis: Vector3<f64>,
    pub v_axis: Vector3<f64>,
    pub width: f64,
    pub height: f64,
    pub texture: Texture,
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

#[cfg(test)]
mod tests {
    use super::*;

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
