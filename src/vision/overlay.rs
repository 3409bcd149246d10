//! The estimator's debug image: the camera frame as RGB8 with the detected marker drawn on
//! it (its outline in green, its corner 0 in red, the centre as a cross), so that a
//! surgeon-engineer sees in RViz what the estimator saw.

use super::{ImageView, MarkerDetection, VisionError};

/// An owned RGB8 image, row-major, no padding.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    /// Pixels, `3 * width * height` bytes.
    pub data: Vec<u8>,
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
}

/// Colour order of 3- and 4-channel input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChannelOrder {
    /// Red first (rgb8, rgba8).
    Rgb,
    /// Blue first (bgr8, bgra8: the ZED's order).
    Bgr,
}

const GREEN: [u8; 3] = [40, 220, 60];
const RED: [u8; 3] = [230, 40, 40];

impl RgbImage {
    /// Convert a grey, RGB(A) or BGR(A) view to RGB8.
    pub fn from_view(view: &ImageView<'_>, order: ChannelOrder) -> Result<Self, VisionError> {
        view.validate()?;
        let c = view.channels as usize;
        let mut data = Vec::with_capacity(3 * view.width as usize * view.height as usize);
        for px in view.data.chunks_exact(c) {
            let rgb = match (c, order) {
                (1, _) => [px[0]; 3],
                (_, ChannelOrder::Rgb) => [px[0], px[1], px[2]],
                (_, ChannelOrder::Bgr) => [px[2], px[1], px[0]],
            };
            data.extend_from_slice(&rgb);
        }
        Ok(Self {
            data,
            width: view.width,
            height: view.height,
        })
    }

    fn put(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return;
        }
        let i = 3 * (y as usize * self.width as usize + x as usize);
        self.data[i..i + 3].copy_from_slice(&colour);
    }

    /// Draw a line `thickness` px wide (clipped to the image; non-finite ends draw nothing).
    pub fn line(&mut self, a: [f64; 2], b: [f64; 2], colour: [u8; 3], thickness: u32) {
        if a.iter().chain(&b).any(|v| !v.is_finite() || v.abs() > 1e6) {
            return;
        }
        let steps = ((b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil() as usize).max(1);
        let r = i64::from(thickness / 2);
        for k in 0..=steps {
            let s = k as f64 / steps as f64;
            let (x, y) = (
                (a[0] + s * (b[0] - a[0])).round() as i64,
                (a[1] + s * (b[1] - a[1])).round() as i64,
            );
            for dy in -r..=r {
                for dx in -r..=r {
                    self.put(x + dx, y + dy, colour);
                }
            }
        }
    }

    /// Draw a detection: outline, corner 0 (ArUco top-left, AprilTag left-bottom), centre cross.
    pub fn draw_detection(&mut self, det: &MarkerDetection) {
        let c = det.corners;
        for k in 0..4 {
            self.line(c[k], c[(k + 1) % 4], GREEN, 3);
        }
        let tl = c[0];
        self.line([tl[0] - 6.0, tl[1]], [tl[0] + 6.0, tl[1]], RED, 5);
        let centre = [
            c.iter().map(|p| p[0]).sum::<f64>() / 4.0,
            c.iter().map(|p| p[1]).sum::<f64>() / 4.0,
        ];
        self.line([centre[0] - 8.0, centre[1]], [centre[0] + 8.0, centre[1]], GREEN, 1);
        self.line([centre[0], centre[1] - 8.0], [centre[0], centre[1] + 8.0], GREEN, 1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Isometry3;

    #[test]
    fn converts_channel_orders_and_draws_inside_the_image_only() {
        let bgra = [10u8, 20, 30, 255, 1, 2, 3, 255];
        let v = ImageView::new(&bgra, 2, 1, 4).unwrap();
        let img = RgbImage::from_view(&v, ChannelOrder::Bgr).unwrap();
        assert_eq!(img.data, vec![30, 20, 10, 3, 2, 1]);
        let grey = [7u8; 4];
        let g = RgbImage::from_view(&ImageView::new(&grey, 2, 2, 1).unwrap(), ChannelOrder::Rgb).unwrap();
        assert_eq!(g.data, vec![7; 12]);

        let buf = vec![0u8; 40 * 30];
        let mut img = RgbImage::from_view(&ImageView::new(&buf, 40, 30, 1).unwrap(), ChannelOrder::Rgb).unwrap();
        let det = MarkerDetection {
            id: 0,
            pose_camera_marker: Isometry3::identity(),
            corners: [[10.0, 10.0], [30.0, 10.0], [30.0, 20.0], [-50.0, 20.0]],
            reprojection_error_px: 0.1,
        };
        img.draw_detection(&det);
        let at = |x: usize, y: usize| &img.data[3 * (y * 40 + x)..3 * (y * 40 + x) + 3];
        assert_eq!(at(20, 10), &GREEN);
        assert_eq!(at(30, 15), &GREEN);
        assert_eq!(at(10, 10), &RED);
        assert_eq!(at(5, 5), &[0, 0, 0]);
        img.line([f64::NAN, 0.0], [3.0, 3.0], RED, 1);
        assert_eq!(img.data.len(), 40 * 30 * 3);
    }
}
