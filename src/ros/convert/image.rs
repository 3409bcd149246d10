//! sensor_msgs/Image and CameraInfo to and from the vision types, with the checks a camera
//! message from the wire needs: a supported 8-bit encoding, a row step that fits, a buffer
//! as long as the header says, intrinsics that make sense.
//!
//! A CameraInfo is read as ROS's image_pipeline reads it (`sensor_msgs/CameraInfo.msg`,
//! image_geometry's `PinholeCameraModel`; [`crate::vision::camera`]): the camera of a
//! rectified image (`image_rect`, `image_rect_color`) is P without distortion, that of a raw
//! image (`image_raw`) K and D in the named distortion model. What the simulated camera
//! publishes is what a camera driver with `camera_info_manager` publishes for its raw image:
//! the calibration's K, D, R = identity and P = [K | Tx] (Tx = -fx * baseline).

use std::borrow::Cow;

use super::header;
use crate::ros::msgs::sensor_msgs;
use crate::vision::{CameraInfoFields, CameraModel, ChannelOrder, ImageKind, ImageView, VisionError};

/// The 8-bit encodings the estimator reads: channels and colour order.
pub fn encoding_layout(encoding: &str) -> Result<(u32, ChannelOrder), String> {
    match encoding.to_ascii_lowercase().as_str() {
        "mono8" | "8uc1" => Ok((1, ChannelOrder::Rgb)),
        "rgb8" => Ok((3, ChannelOrder::Rgb)),
        "bgr8" | "8uc3" => Ok((3, ChannelOrder::Bgr)),
        "rgba8" => Ok((4, ChannelOrder::Rgb)),
        "bgra8" | "8uc4" => Ok((4, ChannelOrder::Bgr)),
        other => Err(format!(
            "image encoding '{other}' not supported (mono8, rgb8, bgr8, rgba8, bgra8)"
        )),
    }
}

/// The pixels of an Image, without row padding, and their layout.
#[derive(Debug, Clone)]
pub struct Pixels<'a> {
    /// The rows, packed: borrowed when the message's rows are, copied when its step pads them.
    pub data: Cow<'a, [u8]>,
    /// Channels per pixel.
    pub channels: u32,
    /// The colour order of 3 or 4 channels.
    pub order: ChannelOrder,
}

/// The pixels of an Image, without row padding, with their layout. Borrowed when the rows
/// are packed, copied when the step pads them.
pub fn image_pixels(msg: &sensor_msgs::Image) -> Result<Pixels<'_>, String> {
    let (channels, order) = encoding_layout(&msg.encoding)?;
    let (w, h) = (msg.width as usize, msg.height as usize);
    if w == 0 || h == 0 {
        return Err(format!("image is {}x{}", msg.width, msg.height));
    }
    let row = w * channels as usize;
    let step = msg.step as usize;
    if step < row {
        return Err(format!("image step {step} is shorter than a row of {row} bytes"));
    }
    let need = step.checked_mul(h).ok_or("image size overflows")?;
    if msg.data.len() < need {
        return Err(format!(
            "image data has {} bytes, {}x{} with step {step} needs {need}",
            msg.data.len(),
            msg.width,
            msg.height
        ));
    }
    let data = if step == row {
        Cow::Borrowed(&msg.data[..row * h])
    } else {
        Cow::Owned(msg.data.chunks(step).take(h).flat_map(|r| &r[..row]).copied().collect())
    };
    Ok(Pixels { data, channels, order })
}

/// A checked view of `pixels` (from [`image_pixels`]) with the message's size.
pub fn view<'a>(msg: &sensor_msgs::Image, pixels: &'a [u8], channels: u32) -> Result<ImageView<'a>, VisionError> {
    ImageView::new(pixels, msg.width, msg.height, channels)
}

/// The camera model of the image `kind` a CameraInfo describes: P for a rectified image, K
/// and D for a raw one ([`CameraModel::from_camera_info`]).
pub fn camera_model(msg: &sensor_msgs::CameraInfo, kind: ImageKind) -> Result<CameraModel, VisionError> {
    let mut m = CameraModel::from_camera_info(
        &CameraInfoFields {
            width: msg.width,
            height: msg.height,
            distortion_model: &msg.distortion_model,
            d: &msg.D,
            k: &msg.K,
            r: &msg.R,
            p: &msg.P,
        },
        kind,
    )?;
    m.name = msg.header.frame_id.clone();
    Ok(m)
}

/// The CameraInfo of a camera model (R = identity, P = K | Tx with the stereo baseline).
pub fn camera_info(stamp: rosrust::Time, frame: &str, c: &CameraModel) -> sensor_msgs::CameraInfo {
    let cal = c.to_calibration();
    let mut msg = sensor_msgs::CameraInfo {
        header: header(stamp, frame),
        height: c.height,
        width: c.width,
        distortion_model: cal.distortion_model,
        D: c.distortion.clone(),
        ..Default::default()
    };
    msg.K.copy_from_slice(&cal.camera_matrix.data);
    msg.R.copy_from_slice(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    if let Some(p) = &cal.projection_matrix {
        msg.P.copy_from_slice(&p.data);
    }
    msg
}

/// An Image message of packed 8-bit pixels.
pub fn image(
    stamp: rosrust::Time,
    frame: &str,
    width: u32,
    height: u32,
    encoding: &str,
    channels: u32,
    data: Vec<u8>,
) -> sensor_msgs::Image {
    sensor_msgs::Image {
        header: header(stamp, frame),
        height,
        width,
        encoding: encoding.to_string(),
        is_bigendian: 0,
        step: width * channels,
        data,
    }
}

/// Grey pixels in the layout of `encoding` (grey copied into each colour channel, alpha 255).
pub fn grey_as(encoding: &str, grey: Vec<u8>) -> Result<(Vec<u8>, u32), String> {
    let (channels, _) = encoding_layout(encoding)?;
    Ok(match channels {
        1 => (grey, 1),
        3 => (grey.iter().flat_map(|&g| [g, g, g]).collect(), 3),
        _ => (grey.iter().flat_map(|&g| [g, g, g, 255]).collect(), 4),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::{DistortionModel, ImageKindSetting};

    fn msg(encoding: &str, w: u32, h: u32, step: u32, len: usize) -> sensor_msgs::Image {
        sensor_msgs::Image {
            encoding: encoding.into(),
            width: w,
            height: h,
            step,
            data: (0..len).map(|i| i as u8).collect(),
            ..Default::default()
        }
    }

    #[test]
    fn packed_and_padded_rows_and_bad_buffers() {
        let m = msg("mono8", 3, 2, 3, 6);
        let Pixels {
            data: p, channels: c, ..
        } = image_pixels(&m).unwrap();
        assert!(matches!(p, Cow::Borrowed(_)));
        assert_eq!((p.len(), c), (6, 1));
        let m = msg("bgra8", 2, 2, 12, 24);
        let Pixels {
            data: p,
            channels: c,
            order: o,
        } = image_pixels(&m).unwrap();
        assert_eq!((c, o), (4, ChannelOrder::Bgr));
        assert_eq!(&p[..], &[0, 1, 2, 3, 4, 5, 6, 7, 12, 13, 14, 15, 16, 17, 18, 19]);
        assert!(view(&m, &p, c).is_ok());
        assert!(image_pixels(&msg("mono8", 3, 2, 3, 5)).unwrap_err().contains("needs 6"));
        assert!(image_pixels(&msg("mono8", 3, 2, 2, 6)).unwrap_err().contains("shorter"));
        assert!(image_pixels(&msg("16UC1", 3, 2, 6, 12))
            .unwrap_err()
            .contains("not supported"));
        assert!(image_pixels(&msg("mono8", 0, 2, 0, 0)).is_err());
    }

    /// A calibrated camera's CameraInfo whose P differs from K (as camera_calibration's
    /// P does): fx' 650 and cx' 600 against K's 700 and 640.
    fn info(model: &str, d: &[f64]) -> sensor_msgs::CameraInfo {
        let mut m = sensor_msgs::CameraInfo {
            width: 1280,
            height: 720,
            distortion_model: model.into(),
            D: d.to_vec(),
            ..Default::default()
        };
        m.K.copy_from_slice(&[700.0, 0.0, 640.0, 0.0, 701.0, 360.0, 0.0, 0.0, 1.0]);
        m.R.copy_from_slice(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        m.P.copy_from_slice(&[650.0, 0.0, 600.0, 0.0, 0.0, 651.0, 350.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        m
    }

    const PLUMB_BOB: [f64; 5] = [-0.17, 0.02, 0.0005, -0.0003, 0.001];

    #[test]
    fn a_rectified_image_is_read_with_p_and_no_distortion_a_raw_one_with_k_and_d() {
        let m = info("plumb_bob", &PLUMB_BOB);
        let rect = camera_model(&m, ImageKind::Rectified).unwrap();
        assert_eq!(rect.intrinsics(), [650.0, 651.0, 600.0, 350.0]);
        assert!(rect.distortion.is_empty() && !rect.is_distorted());
        let raw = camera_model(&m, ImageKind::Raw).unwrap();
        assert_eq!(raw.intrinsics(), [700.0, 701.0, 640.0, 360.0]);
        assert_eq!(
            (raw.distortion.as_slice(), raw.distortion_model),
            (&PLUMB_BOB[..], DistortionModel::Rational)
        );
        // A point off the axis lands where each model says: the rectified one through P alone.
        let p = nalgebra::Vector3::new(0.1, -0.05, 0.4);
        let [u, v] = rect.project(&p).unwrap();
        assert!((u - (650.0 * 0.25 + 600.0)).abs() < 1e-9 && (v - (651.0 * -0.125 + 350.0)).abs() < 1e-9);
        let [u, _] = raw.project(&p).unwrap();
        let r2: f64 = 0.25 * 0.25 + 0.125 * 0.125;
        let radial = 1.0 - 0.17 * r2 + 0.02 * r2 * r2 + 0.001 * r2 * r2 * r2;
        let xd = 0.25 * radial + 2.0 * 0.0005 * 0.25 * -0.125 - 0.0003 * (r2 + 2.0 * 0.25 * 0.25);
        assert!((u - (700.0 * xd + 640.0)).abs() < 1e-9, "{u}");
        // The rectified image of a ZED (zero D, P = K) and a driver's D = [] are no distortion.
        let zed = info("plumb_bob", &[0.0; 5]);
        assert!(!camera_model(&zed, ImageKind::Raw).unwrap().is_distorted());
        assert!(!camera_model(&info("plumb_bob", &[]), ImageKind::Raw)
            .unwrap()
            .is_distorted());
        // The right camera of a stereo pair: its baseline from P's Tx, read either way.
        let mut right = info("plumb_bob", &PLUMB_BOB);
        right.P[3] = -650.0 * 0.063;
        for kind in [ImageKind::Rectified, ImageKind::Raw] {
            assert!((camera_model(&right, kind).unwrap().baseline_m - 0.063).abs() < 1e-12);
        }
        // Which kind an image topic is, by its last name, unless the parameter says.
        for (topic, kind) in [
            ("/zedm/zed_node/left/image_rect_color", ImageKind::Rectified),
            ("/camera/image_rect", ImageKind::Rectified),
            ("/sim_camera/left/image_raw", ImageKind::Raw),
            ("/camera/image_color", ImageKind::Raw),
            ("/camera/image_rect_color/compressed_not", ImageKind::Raw),
            ("image_rect", ImageKind::Rectified),
        ] {
            assert_eq!(ImageKind::of_topic(topic), kind, "{topic}");
            assert_eq!(ImageKindSetting::ByTopicName.resolve(topic), kind);
        }
        assert_eq!(ImageKindSetting::Raw.resolve("/a/image_rect"), ImageKind::Raw);
        assert_eq!(
            ImageKindSetting::Rectified.resolve("/a/image_raw"),
            ImageKind::Rectified
        );
    }

    #[test]
    fn each_distortion_model_of_a_raw_image_and_its_round_trip() {
        let rational = [-0.2, 0.05, 0.0004, -0.0002, 0.001, 0.01, 0.002, 0.0005];
        let fisheye = [0.05, -0.01, 0.002, -0.0005];
        for (name, d, model) in [
            ("plumb_bob", &PLUMB_BOB[..], DistortionModel::Rational),
            ("rational_polynomial", &rational[..], DistortionModel::Rational),
            ("equidistant", &fisheye[..], DistortionModel::Equidistant),
        ] {
            let c = camera_model(&info(name, d), ImageKind::Raw).unwrap();
            assert_eq!((c.distortion.as_slice(), c.distortion_model), (d, model), "{name}");
            assert!(c.is_distorted());
            // What the simulated camera publishes of a model reads back as the same model.
            let out = camera_info(rosrust::Time::new(), "cam", &c);
            assert_eq!((out.distortion_model.as_str(), out.R), (name, info(name, d).R));
            assert_eq!(&out.P[..4], &[700.0, 0.0, 640.0, 0.0], "P = [K | 0]");
            let mut back = camera_model(&out, ImageKind::Raw).unwrap();
            back.name.clear();
            assert_eq!(back, c, "{name}");
        }
        // The equidistant model bends a ray at angle θ to θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)
        // (cv::fisheye::projectPoints), not to tan θ.
        let c = camera_model(&info("equidistant", &fisheye), ImageKind::Raw).unwrap();
        let theta = (0.5f64).atan();
        let t2 = theta * theta;
        let theta_d = theta * (1.0 + 0.05 * t2 - 0.01 * t2 * t2 + 0.002 * t2.powi(3) - 0.0005 * t2.powi(4));
        let [u, v] = c.project(&nalgebra::Vector3::new(0.3, 0.4, 1.0)).unwrap();
        assert!((u - (700.0 * theta_d * 0.6 + 640.0)).abs() < 1e-9, "{u}");
        assert!((v - (701.0 * theta_d * 0.8 + 360.0)).abs() < 1e-9, "{v}");
        assert!(c.project(&nalgebra::Vector3::new(0.0, 0.0, 1.0)).unwrap() == [640.0, 360.0]);
        // Its rectified camera (what image_proc's image_rect is, P = K) has none.
        let r = c.rectified();
        assert!(!r.is_distorted() && r.intrinsics() == c.intrinsics());
    }

    fn refused(m: &sensor_msgs::CameraInfo, kind: ImageKind, says: &str) {
        let e = camera_model(m, kind).unwrap_err().to_string();
        assert!(e.contains(says), "{kind:?}: '{e}' does not say '{says}'");
    }

    #[test]
    fn bad_camera_info_is_refused_with_the_reason() {
        // An unknown model, named (a raw image needs it; a rectified one has no distortion).
        refused(
            &info("kannala_brandt", &[0.0; 4]),
            ImageKind::Raw,
            "'kannala_brandt' not supported",
        );
        refused(&info("", &[]), ImageKind::Raw, "'' not supported");
        assert!(camera_model(&info("kannala_brandt", &[0.0; 4]), ImageKind::Rectified).is_ok());
        // Wrong lengths for each model.
        refused(
            &info("plumb_bob", &[0.1; 4]),
            ImageKind::Raw,
            "'plumb_bob' has 5 coefficients, D has 4",
        );
        refused(
            &info("plumb_bob", &[0.1; 8]),
            ImageKind::Raw,
            "has 5 coefficients, D has 8",
        );
        refused(
            &info("rational_polynomial", &PLUMB_BOB),
            ImageKind::Raw,
            "has 8 coefficients, D has 5",
        );
        refused(
            &info("equidistant", &PLUMB_BOB),
            ImageKind::Raw,
            "has 4 coefficients, D has 5",
        );
        refused(&info("equidistant", &[]), ImageKind::Raw, "has 4 coefficients, D has 0");
        // NaN anywhere, read either way.
        for kind in [ImageKind::Raw, ImageKind::Rectified] {
            let mut m = info("plumb_bob", &PLUMB_BOB);
            m.K[4] = f64::NAN;
            refused(&m, kind, "non-finite");
            let mut m = info("plumb_bob", &PLUMB_BOB);
            m.P[2] = f64::INFINITY;
            refused(&m, kind, "non-finite");
            let mut m = info("plumb_bob", &PLUMB_BOB);
            m.D[1] = f64::NAN;
            refused(&m, kind, "non-finite");
        }
        // Zero focal lengths: K's for a raw image, P's for a rectified one (an uncalibrated
        // camera leaves both zero).
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.K[0] = 0.0;
        refused(&m, ImageKind::Raw, "K[0] = 0");
        assert!(camera_model(&m, ImageKind::Rectified).is_ok());
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.P = [0.0; 12];
        refused(&m, ImageKind::Rectified, "P[0] = 0");
        assert_eq!(camera_model(&m, ImageKind::Raw).unwrap().baseline_m, 0.0);
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.P[5] = 0.0;
        refused(&m, ImageKind::Rectified, "P[5] = 0");
        // A vertical pair, a 5 m baseline, a raw right image off the rectified frame.
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.P[7] = -30.0;
        refused(&m, ImageKind::Rectified, "Ty");
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.P[3] = -650.0 * 5.0;
        refused(&m, ImageKind::Rectified, "baseline");
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.P[3] = -650.0 * 0.063;
        m.R.copy_from_slice(&[0.9998, -0.02, 0.0, 0.02, 0.9998, 0.0, 0.0, 0.0, 1.0]);
        refused(&m, ImageKind::Raw, "read its image_rect");
        assert!(camera_model(&m, ImageKind::Rectified).is_ok());
        // Absurd sizes and principal points still go through the model's own checks.
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.width = 0;
        refused(&m, ImageKind::Raw, "image size");
        let mut m = info("plumb_bob", &PLUMB_BOB);
        m.P[2] = 1e6;
        refused(&m, ImageKind::Rectified, "principal point");
    }

    #[test]
    fn grey_in_each_encoding() {
        assert_eq!(grey_as("mono8", vec![5, 6]).unwrap(), (vec![5, 6], 1));
        assert_eq!(grey_as("rgb8", vec![5]).unwrap(), (vec![5, 5, 5], 3));
        assert_eq!(grey_as("bgra8", vec![5]).unwrap(), (vec![5, 5, 5, 255], 4));
        assert!(grey_as("yuv422", vec![5]).is_err());
    }
}
