//! Image buffers that cross the bridge: 8-bit grey or RGB, row-major, no padding.

use std::path::Path;

use super::VisionError;
use crate::ffi::vision::ffi;

/// A borrowed 8-bit image, row-major, no padding: `channels` = 1 (mono8), 3 (rgb8 or bgr8)
/// or 4 (rgba8 or bgra8, as the ZED publishes). Detection works on grey; the colour order
/// only changes the grey weights slightly.
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a> {
    /// Pixels, `width * height * channels` bytes.
    pub data: &'a [u8],
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// 1 (grey), 3 (RGB8/BGR8) or 4 (RGBA8/BGRA8).
    pub channels: u32,
}

impl<'a> ImageView<'a> {
    /// A checked view: the buffer length must match the size; channels 1 or 3.
    pub fn new(data: &'a [u8], width: u32, height: u32, channels: u32) -> Result<Self, VisionError> {
        let v = Self {
            data,
            width,
            height,
            channels,
        };
        v.validate()?;
        Ok(v)
    }

    /// A grey view of `data` with the size of `camera`'s images (unchecked: the renderers
    /// of that camera make buffers of its size; [`ImageView::validate`] checks).
    pub fn grey(data: &'a [u8], camera: &super::CameraModel) -> Self {
        Self {
            data,
            width: camera.width,
            height: camera.height,
            channels: 1,
        }
    }

    /// Check size, channels and buffer length.
    pub fn validate(&self) -> Result<(), VisionError> {
        if self.width == 0 || self.height == 0 {
            return Err(VisionError::InvalidInput("empty image".into()));
        }
        if self.width > 20_000 || self.height > 20_000 {
            return Err(VisionError::InvalidInput("image larger than 20000 px".into()));
        }
        if !matches!(self.channels, 1 | 3 | 4) {
            return Err(VisionError::InvalidInput(format!(
                "{} channels: grey (1), RGB8/BGR8 (3) or RGBA8/BGRA8 (4) are supported",
                self.channels
            )));
        }
        let need = self.width as usize * self.height as usize * self.channels as usize;
        if self.data.len() != need {
            return Err(VisionError::InvalidInput(format!(
                "buffer has {} bytes, {}x{}x{} needs {need}",
                self.data.len(),
                self.width,
                self.height,
                self.channels
            )));
        }
        Ok(())
    }
}

/// An owned 8-bit grey image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct GreyImage {
    /// Pixels, `width * height` bytes.
    pub data: Vec<u8>,
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
}

impl GreyImage {
    /// A view of this image.
    pub fn view(&self) -> ImageView<'_> {
        ImageView {
            data: &self.data,
            width: self.width,
            height: self.height,
            channels: 1,
        }
    }

    /// Read any image file OpenCV reads (PNG, PGM, JPEG…) as grey.
    pub fn read(path: &Path) -> Result<Self, VisionError> {
        let p = path
            .to_str()
            .ok_or_else(|| VisionError::Io(format!("non-UTF-8 path {}", path.display())))?;
        let mut dims = [0i32; 2];
        let data = ffi::read_image(p, 1, &mut dims).map_err(|e| VisionError::Io(e.what().to_string()))?;
        let (w, h) = (u32::try_from(dims[0]), u32::try_from(dims[1]));
        match (w, h) {
            (Ok(width), Ok(height)) if data.len() == width as usize * height as usize => {
                Ok(Self { data, width, height })
            }
            _ => Err(VisionError::Io(format!("{}: unexpected image size", path.display()))),
        }
    }

    /// Write the image; the format follows the extension (`.png`, `.pgm`, `.jpg`…).
    pub fn write(&self, path: &Path) -> Result<(), VisionError> {
        self.view().validate()?;
        let p = path
            .to_str()
            .ok_or_else(|| VisionError::Io(format!("non-UTF-8 path {}", path.display())))?;
        ffi::write_image(p, &self.data, self.width as i32, self.height as i32, 1)
            .map_err(|e| VisionError::Io(e.what().to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_rejects_bad_buffers() {
        let buf = vec![0u8; 12];
        assert!(ImageView::new(&buf, 4, 3, 1).is_ok());
        assert!(ImageView::new(&buf, 2, 2, 3).is_ok());
        assert!(ImageView::new(&buf, 4, 4, 1).is_err());
        assert!(ImageView::new(&buf, 0, 3, 1).is_err());
        assert!(ImageView::new(&buf, 3, 2, 2).is_err());
        assert!(ImageView::new(&buf, 3, 1, 4).is_ok());
        assert!(ImageView::new(&buf, 2, 1, 6).is_err());
    }

    #[test]
    fn png_round_trip() {
        let img = GreyImage {
            data: (0..=255u8).cycle().take(64 * 32).collect(),
            width: 64,
            height: 32,
        };
        let p = std::env::temp_dir().join(format!("vision_rt_{}.png", std::process::id()));
        img.write(&p).unwrap();
        let back = GreyImage::read(&p).unwrap();
        let _ = std::fs::remove_file(&p);
        assert_eq!(back, img);
        assert!(GreyImage::read(Path::new("/nonexistent/x.png")).is_err());
    }
}
