//! sensor_msgs/Image and CameraInfo to and from the vision types, with the checks a camera
//! message from the wire needs: a supported 8-bit encoding, a row step that fits, a buffer
//! as long as the header says, intrinsics that make sense.

use std::borrow::Cow;

use super::header;
use crate::ros::msgs::sensor_msgs;
use crate::vision::{CameraModel, ChannelOrder, ImageView, VisionError};

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

/// The camera model of a CameraInfo (K, D, distortion model, size).
pub fn camera_model(msg: &sensor_msgs::CameraInfo) -> Result<CameraModel, VisionError> {
    let mut m = CameraModel::from_camera_info(msg.width, msg.height, &msg.K, &msg.D, &msg.distortion_model)?;
    m.name = msg.header.frame_id.clone();
    // A zero P (a CameraInfo without a projection) leaves the baseline at 0.
    if msg.P[0] > 0.0 {
        m.set_baseline_from_projection(&msg.P)?;
    }
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

    #[test]
    fn camera_info_round_trip_and_bad_intrinsics() {
        let mut c = CameraModel::pinhole(640, 360, 350.0, 351.0, 320.5, 180.2).unwrap();
        c.distortion = vec![-0.17, 0.02, 0.0005, -0.0003, 0.0];
        let info = camera_info(rosrust::Time::new(), "cam", &c);
        let mut back = camera_model(&info).unwrap();
        back.name.clear();
        assert_eq!(back, c);
        // The right camera of a stereo pair carries its baseline in P's Tx.
        let right = CameraModel {
            baseline_m: 0.063,
            ..c.clone()
        };
        let info_r = camera_info(rosrust::Time::new(), "cam", &right);
        assert!((info_r.P[3] + 350.0 * 0.063).abs() < 1e-12);
        assert!((camera_model(&info_r).unwrap().baseline_m - 0.063).abs() < 1e-12);
        let mut bad = info_r.clone();
        bad.P[3] = 350.0 * 5.0;
        assert!(camera_model(&bad).is_err(), "a 5 m baseline");
        let mut bad = info.clone();
        bad.K[0] = f64::NAN;
        assert!(camera_model(&bad).is_err());
        bad = info;
        bad.distortion_model = "equidistant".into();
        assert!(camera_model(&bad).is_err());
    }

    #[test]
    fn grey_in_each_encoding() {
        assert_eq!(grey_as("mono8", vec![5, 6]).unwrap(), (vec![5, 6], 1));
        assert_eq!(grey_as("rgb8", vec![5]).unwrap(), (vec![5, 5, 5], 3));
        assert_eq!(grey_as("bgra8", vec![5]).unwrap(), (vec![5, 5, 5, 255], 4));
        assert!(grey_as("yuv422", vec![5]).is_err());
    }
}
