//! Writing rendered frames to disk as PNG, OpenEXR or raw `f32` depth.
//!
//! A [`Frame`] holds linear RGB colours and per-pixel hit distances in row-major
//! order with `y = 0` as the top row. [`write_png`] stores 8-bit sRGB, [`write_exr`]
//! stores linear `f32` R, G, B and Z channels, and [`write_depth_f32`] dumps the depth
//! buffer as little-endian `f32` values. [`write_image`] picks PNG or EXR from the file
//! extension. Every writer goes through one atomic helper that writes a temporary file
//! in the target directory, syncs it and renames it onto the target, so a failed write
//! never leaves a partial image or a stray temporary file behind.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// A rendered frame: row-major, y = 0 is the TOP row. `rgb` are linear colours in \[0,1\] (may exceed),
/// `depth` is the hit distance per pixel, f32::INFINITY for a miss.
pub struct Frame {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// `width · height` colours.
    pub rgb: Vec<[f32; 3]>,
    /// `width · height` hit distances.
    pub depth: Vec<f32>,
}

/// An error raised while writing an image file.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The file system refused an operation on `path`.
    #[error("cannot write {}: {source}", .path.display())]
    Io {
        /// The image file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// The encoder rejected the frame or failed for a reason other than I/O.
    #[error("cannot encode {}: {message}", .path.display())]
    Encode {
        /// The image file.
        path: PathBuf,
        /// The encoder's message.
        message: String,
    },
    /// The extension of `path` is neither `.png` nor `.exr`.
    #[error(
        "cannot write {}: unknown image extension (expected .png or .exr)",
        .path.display()
    )]
    UnknownExtension {
        /// The file asked for.
        path: PathBuf,
    },
}

/// Builds an `Io` error for `path`.
fn io_err(path: &Path, source: std::io::Error) -> ImageError {
    ImageError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Checks that the buffers of `frame` match its dimensions before anything touches the disk.
fn check_frame(path: &Path, frame: &Frame) -> Result<usize, ImageError> {
    let pixels = frame.width as usize * frame.height as usize;
    if pixels == 0 || frame.rgb.len() != pixels || frame.depth.len() != pixels {
        return Err(ImageError::Encode {
            path: path.to_path_buf(),
            message: format!(
                "frame is {}x{} but has {} colours and {} depths",
                frame.width,
                frame.height,
                frame.rgb.len(),
                frame.depth.len()
            ),
        });
    }
    Ok(pixels)
}

/// Runs `f` on a temporary file next to `path`, then syncs it and renames it onto `path`
/// ([`crate::fsio::write_atomically`]). On any error the temporary file is removed and the
/// target is left untouched.
fn write_atomically(
    path: &Path,
    f: impl FnOnce(&mut BufWriter<&mut File>) -> Result<(), ImageError>,
) -> Result<(), ImageError> {
    if path.file_name().is_none() {
        return Err(ImageError::UnknownExtension {
            path: path.to_path_buf(),
        });
    }
    crate::fsio::write_atomically(
        path,
        |e| io_err(path, e),
        |file| {
            let mut writer = BufWriter::new(file);
            f(&mut writer)?;
            writer
                .into_inner()
                .map_err(|e| io_err(path, e.into_error()))?;
            Ok(())
        },
    )
}

/// Converts one linear value to an 8-bit sRGB code value.
fn linear_to_srgb8(v: f32) -> u8 {
    // A NaN survives `clamp`, but the saturating `as u8` cast below maps it to 0 (black).
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

/// Writes 8-bit sRGB PNG (RGB, apply the sRGB transfer function to linear values, clamp to \[0,1\], round).
pub fn write_png(path: &Path, frame: &Frame) -> Result<(), ImageError> {
    check_frame(path, frame)?;
    let data: Vec<u8> = frame
        .rgb
        .iter()
        .flat_map(|c| c.map(linear_to_srgb8))
        .collect();
    write_atomically(path, |w| {
        let png_err = |e: png::EncodingError| match e {
            png::EncodingError::IoError(source) => io_err(path, source),
            other => ImageError::Encode {
                path: path.to_path_buf(),
                message: other.to_string(),
            },
        };
        let mut encoder = png::Encoder::new(w, frame.width, frame.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut writer = encoder.write_header().map_err(png_err)?;
        writer.write_image_data(&data).map_err(png_err)?;
        writer.finish().map_err(png_err)
    })
}

/// Writes an OpenEXR file with channels R, G, B (f32, linear) and Z (f32
/// depth; +inf for a miss), ZIP-compressed (lossless). y=0 is the top row
/// of the image as EXR viewers show it.
pub fn write_exr(path: &Path, frame: &Frame) -> Result<(), ImageError> {
    use exr::prelude::*;

    check_frame(path, frame)?;
    let size = (frame.width as usize, frame.height as usize);
    let component = |i: usize| FlatSamples::F32(frame.rgb.iter().map(|c| c[i]).collect());
    let mut list = SmallVec::<[AnyChannel<FlatSamples>; 4]>::with_capacity(4);
    list.push(AnyChannel::new("R", component(0)));
    list.push(AnyChannel::new("G", component(1)));
    list.push(AnyChannel::new("B", component(2)));
    list.push(AnyChannel::new("Z", FlatSamples::F32(frame.depth.clone())));
    // EXR flat samples are stored row by row with increasing y going down the
    // display, so the frame's top-first row order maps across unchanged.
    // Lossless ZIP in 16-line blocks: run-length encoding leaves float
    // channels as large as uncompressed (the default view at 640×480:
    // 4.4 MB with it, 0.34 MB with ZIP).
    let image =
        Image::from_encoded_channels(size, Encoding::SMALL_LOSSLESS, AnyChannels::sort(list));
    write_atomically(path, |w| {
        image.write().to_buffered(w).map_err(|e| match e {
            exr::error::Error::Io(source) => io_err(path, source),
            other => ImageError::Encode {
                path: path.to_path_buf(),
                message: other.to_string(),
            },
        })
    })
}

/// Dispatch on the extension (case-insensitive): .png -> write_png, .exr -> write_exr, else UnknownExtension.
pub fn write_image(path: &Path, frame: &Frame) -> Result<(), ImageError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("png") => write_png(path, frame),
        Some("exr") => write_exr(path, frame),
        _ => Err(ImageError::UnknownExtension {
            path: path.to_path_buf(),
        }),
    }
}

/// Writes W*H little-endian f32 values of frame.depth, row-major, y = 0 first.
pub fn write_depth_f32(path: &Path, frame: &Frame) -> Result<(), ImageError> {
    check_frame(path, frame)?;
    write_atomically(path, |w| {
        frame
            .depth
            .iter()
            .try_for_each(|d| w.write_all(&d.to_le_bytes()))
            .map_err(|e| io_err(path, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Creates a fresh, empty directory unique to one test.
    fn test_dir(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("image_out_test_{}_{}", std::process::id(), name));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// Builds a 5x3 frame whose pixels all differ, with one miss at pixel 7.
    fn sample_frame() -> Frame {
        let (width, height) = (5u32, 3u32);
        let n = (width * height) as usize;
        let rgb = (0..n)
            .map(|i| {
                [
                    i as f32 / 14.0,
                    1.0 - i as f32 / 14.0,
                    0.25 + i as f32 * 0.01,
                ]
            })
            .collect();
        let depth = (0..n)
            .map(|i| {
                if i == 7 {
                    f32::INFINITY
                } else {
                    1.5 + i as f32
                }
            })
            .collect();
        Frame {
            width,
            height,
            rgb,
            depth,
        }
    }

    /// Lists the entries of `dir` by name.
    fn entries(dir: &Path) -> Vec<String> {
        crate::fsio::entry_names(dir).unwrap()
    }

    /// Writes the sample frame with `write` to `file` in a fresh test
    /// directory `dir`, which then holds that file alone; returns the
    /// directory, the file's path and the frame.
    fn write_sample(
        dir: &str,
        file: &str,
        write: fn(&Path, &Frame) -> Result<(), ImageError>,
    ) -> (PathBuf, PathBuf, Frame) {
        let dir = test_dir(dir);
        let path = dir.join(file);
        let frame = sample_frame();
        write(&path, &frame).unwrap();
        assert_eq!(entries(&dir), vec![file.to_string()]);
        (dir, path, frame)
    }

    #[test]
    fn png_round_trip() {
        let (dir, path, frame) = write_sample("png", "out.PNG", write_image);

        let file = std::io::BufReader::new(File::open(&path).unwrap());
        let mut reader = png::Decoder::new(file).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (5, 3));
        assert_eq!(info.color_type, png::ColorType::Rgb);
        // The top-left pixel is frame pixel 0: linear (0, 1, 0.25).
        assert_eq!(&buf[0..3], &[0, 255, linear_to_srgb8(0.25)]);
        assert_eq!(linear_to_srgb8(0.25), 137);
        assert_eq!(linear_to_srgb8(f32::NAN), 0);
        assert_eq!(linear_to_srgb8(7.0), 255);
        // Pixel (x = 2, y = 1) is frame pixel 7.
        let expected = frame.rgb[7].map(linear_to_srgb8);
        assert_eq!(&buf[21..24], &expected);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn exr_round_trip() {
        use exr::prelude::*;

        let (dir, path, frame) = write_sample("exr", "out.exr", write_image);

        let image = read_all_flat_layers_from_file(&path).unwrap();
        let layer = &image.layer_data[0];
        assert_eq!(layer.size, Vec2(5, 3));
        assert_eq!(layer.encoding.compression, Compression::ZIP16);
        let channel = |name: &str| -> Vec<f32> {
            let c = layer
                .channel_data
                .list
                .iter()
                .find(|c| c.name == *name)
                .unwrap_or_else(|| panic!("missing channel {name}"));
            match &c.sample_data {
                FlatSamples::F32(v) => v.clone(),
                other => panic!("channel {name} is not f32: {other:?}"),
            }
        };
        let r: Vec<f32> = frame.rgb.iter().map(|c| c[0]).collect();
        let b: Vec<f32> = frame.rgb.iter().map(|c| c[2]).collect();
        assert_eq!(channel("R"), r);
        assert_eq!(channel("B"), b);
        assert_eq!(channel("Z"), frame.depth);
        assert_eq!(channel("Z")[7], f32::INFINITY);
        // The first stored sample is the top-left pixel, frame pixel 0.
        assert_eq!(channel("G")[0], 1.0);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn depth_f32_layout() {
        let (dir, path, frame) = write_sample("depth", "depth.bin", write_depth_f32);
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(bytes.len(), 5 * 3 * 4);
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(values, frame.depth);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn missing_directory_is_io_error() {
        let dir = test_dir("missing");
        let path = dir.join("no_such_dir").join("out.png");
        let err = write_image(&path, &sample_frame()).unwrap_err();
        assert!(matches!(err, ImageError::Io { .. }), "{err:?}");
        assert!(err.to_string().contains(&path.display().to_string()));
        assert!(std::error::Error::source(&err).is_some());
        assert!(entries(&dir).is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn failed_encode_leaves_nothing_behind() {
        let dir = test_dir("fail");
        let path = dir.join("out.bin");
        let result = write_atomically(&path, |w| {
            w.write_all(b"partial").unwrap();
            Err(ImageError::Encode {
                path: path.clone(),
                message: "boom".into(),
            })
        });
        assert!(result.is_err());
        assert!(entries(&dir).is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn unknown_extension_is_rejected() {
        let frame = sample_frame();
        for name in ["out.jpg", "out"] {
            let path = std::env::temp_dir().join(name);
            let err = write_image(&path, &frame).unwrap_err();
            assert!(
                matches!(err, ImageError::UnknownExtension { .. }),
                "{err:?}"
            );
            assert!(err.to_string().contains(name));
        }
    }
}
