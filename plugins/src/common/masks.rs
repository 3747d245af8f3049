//! Mask morphology shared by the stages that widen a mask (the reflection stage's inpainted
//! region, the trackers' photometric margin around highlights).

use capsule_slam_framework::Mask;

/// `mask` dilated by a disc of `radius_px` (0 = unchanged), limited to `within` if given.
pub fn dilate(mask: &Mask, radius_px: usize, within: Option<&Mask>) -> Mask {
    if radius_px == 0 {
        return mask.clone();
    }
    let (w, h) = mask.size();
    let r = radius_px as isize;
    let offsets: Vec<(isize, isize)> = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))).filter(|(dx, dy)| dx * dx + dy * dy <= r * r).collect();
    let mut out = mask.clone();
    for k in 0..w * h {
        if !mask.data()[k] {
            continue;
        }
        let (x, y) = ((k % w) as isize, (k / w) as isize);
        for (dx, dy) in &offsets {
            let (nx, ny) = (x + dx, y + dy);
            if nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h {
                let q = ny as usize * w + nx as usize;
                if within.is_none_or(|m| m.data()[q]) {
                    out.data_mut()[q] = true;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pixel_grows_to_a_disc_cut_by_the_limit() {
        let mut m = Mask::new(9, 9);
        *m.at_mut(4, 4) = true;
        let d = dilate(&m, 2, None);
        // A disc of radius 2: 13 pixels (the 5 × 5 square without its corners and their
        // neighbours beyond the radius).
        assert_eq!(d.data().iter().filter(|v| **v).count(), 13);
        assert!(d.at(4, 2) && d.at(3, 3) && !d.at(2, 2) && !d.at(4, 1));
        let mut left = Mask::new(9, 9);
        left.data_mut().iter_mut().enumerate().for_each(|(k, v)| *v = k % 9 <= 4);
        let cut = dilate(&m, 2, Some(&left));
        assert!(cut.at(3, 4) && !cut.at(5, 4) && cut.at(4, 4));
        assert_eq!(dilate(&m, 0, None), m);
    }
}
