//! Least-squares similarity alignment of point sets: Umeyama (1991), "Least-squares
//! estimation of transformation parameters between two point patterns", IEEE TPAMI 13(4),
//! doi:10.1109/34.88573, Eqs. (40)–(42).

use nalgebra::{Matrix3, Point3, Vector3};

/// `x ↦ s R x + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    /// Scale s (1 for a rigid alignment).
    pub scale: f64,
    /// Rotation R.
    pub rotation: Matrix3<f64>,
    /// Translation t.
    pub translation: Vector3<f64>,
}

impl Similarity {
    /// Applies the transform to a point.
    pub fn apply(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.scale * (self.rotation * p.coords) + self.translation)
    }
}

/// The similarity (or, without scale, the rigid transform) that best maps `src` onto `dst`.
/// `None` if the sets differ in length, have fewer than 3 points or are degenerate.
pub fn umeyama(src: &[Point3<f64>], dst: &[Point3<f64>], with_scale: bool) -> Option<Similarity> {
    let n = src.len();
    if n != dst.len() || n < 3 {
        return None;
    }
    let nf = n as f64;
    let mu_s = src.iter().map(|p| p.coords).sum::<Vector3<f64>>() / nf;
    let mu_d = dst.iter().map(|p| p.coords).sum::<Vector3<f64>>() / nf;
    let var_s = src.iter().map(|p| (p.coords - mu_s).norm_squared()).sum::<f64>() / nf;
    let cov: Matrix3<f64> = src.iter().zip(dst).map(|(s, d)| (d.coords - mu_d) * (s.coords - mu_s).transpose()).sum::<Matrix3<f64>>() / nf; // Eq. (38)
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut sign = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        sign[(2, 2)] = -1.0; // Eq. (39)
    }
    let rotation = u * sign * v_t; // Eq. (40)
    let scale = if with_scale {
        if var_s <= 0.0 {
            return None;
        }
        (Matrix3::from_diagonal(&svd.singular_values) * sign).trace() / var_s // Eq. (42)
    } else {
        1.0
    };
    let translation = mu_d - scale * rotation * mu_s; // Eq. (41)
    Some(Similarity { scale, rotation, translation })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn recovers_a_known_similarity() {
        let r = Rotation3::from_euler_angles(0.3, -0.2, 1.1);
        let (s, t) = (2.5, Vector3::new(0.1, -0.4, 0.7));
        let src: Vec<Point3<f64>> = (0..20).map(|i| Point3::new((i as f64).sin(), (i as f64 * 0.7).cos(), i as f64 * 0.05)).collect();
        let dst: Vec<Point3<f64>> = src.iter().map(|p| Point3::from(s * (r * p.coords) + t)).collect();
        let sim = umeyama(&src, &dst, true).unwrap();
        assert!((sim.scale - s).abs() < 1e-12);
        assert!((sim.rotation - r.matrix()).norm() < 1e-12);
        assert!((sim.translation - t).norm() < 1e-12);
        let rigid = umeyama(&src, &dst, false).unwrap();
        assert_eq!(rigid.scale, 1.0);
        assert!((rigid.rotation - r.matrix()).norm() < 1e-9);
    }

    #[test]
    fn degenerate_inputs_give_none() {
        let p = vec![Point3::origin(); 2];
        assert!(umeyama(&p, &p, false).is_none());
        let p3 = vec![Point3::origin(); 3];
        assert!(umeyama(&p3, &p3, true).is_none());
    }
}
