//! The real [`V4l2Device`]: a `/dev/video*` node through the `v4l` crate (ioctls on the
//! node, an mmap buffer stream).

use super::{
    BufferMeta, Capabilities, ControlInfo, ControlKind, Format, FourCc, StampSource, V4l2Device,
};
use std::io;
use std::time::Duration;
use v4l::buffer::{Flags as BufferFlags, Type};
use v4l::capability::Flags as CapabilityFlags;
use v4l::control::{Control, Flags as ControlFlags, Type as ControlType, Value};
use v4l::io::mmap::Stream;
use v4l::io::traits::{CaptureStream, Stream as _};
use v4l::video::Capture;

/// An open V4L2 device node.
pub struct Node {
    device: v4l::Device,
    stream: Option<Stream<'static>>,
}

impl Node {
    /// Open the node at `path` (`/dev/videoN`).
    pub fn open(path: &str) -> io::Result<Node> {
        Ok(Node {
            device: v4l::Device::with_path(path)?,
            stream: None,
        })
    }

    /// Stop `stream`. The `v4l` crate stops it again when dropped and panics if that fails
    /// for any reason but `ENODEV`: a stream that would is forgotten (its buffers stay
    /// mapped) instead.
    fn stop_stream(stream: Stream<'static>) -> io::Result<()> {
        let mut stream = stream;
        match stream.stop() {
            Ok(()) => Ok(()),
            Err(e) if e.raw_os_error() == Some(libc::ENODEV) => Err(e),
            Err(e) => {
                std::mem::forget(stream);
                Err(e)
            }
        }
    }
}

impl V4l2Device for Node {
    fn capabilities(&self) -> io::Result<Capabilities> {
        let caps = self.device.query_caps()?;
        Ok(Capabilities {
            capture: caps.capabilities.contains(CapabilityFlags::VIDEO_CAPTURE),
            streaming: caps.capabilities.contains(CapabilityFlags::STREAMING),
            driver: caps.driver,
            card: caps.card,
            bus: caps.bus,
        })
    }

    fn formats(&self) -> io::Result<Vec<FourCc>> {
        Ok(self
            .device
            .enum_formats()?
            .into_iter()
            .map(|d| FourCc(d.fourcc.repr))
            .collect())
    }

    fn set_format(&mut self, format: Format) -> io::Result<Format> {
        let mut f = self.device.format()?;
        f.width = format.width;
        f.height = format.height;
        f.fourcc = v4l::FourCC::new(&format.fourcc.0);
        f.stride = format.stride;
        let set = self.device.set_format(&f)?;
        Ok(Format {
            fourcc: FourCc(set.fourcc.repr),
            width: set.width,
            height: set.height,
            stride: set.stride,
        })
    }

    fn controls(&self) -> io::Result<Vec<ControlInfo>> {
        Ok(self
            .device
            .query_controls()?
            .into_iter()
            .map(|d| ControlInfo {
                id: d.id,
                kind: match d.typ {
                    ControlType::Integer => ControlKind::Integer,
                    ControlType::Integer64 => ControlKind::Integer64,
                    ControlType::Boolean => ControlKind::Boolean,
                    ControlType::Menu | ControlType::IntegerMenu => ControlKind::Menu(
                        d.items
                            .iter()
                            .flatten()
                            .map(|(i, _)| i64::from(*i))
                            .collect(),
                    ),
                    _ => ControlKind::Other,
                },
                name: d.name,
                min: d.minimum,
                max: d.maximum,
                step: d.step.max(1),
                read_only: d
                    .flags
                    .intersects(ControlFlags::READ_ONLY | ControlFlags::DISABLED),
            })
            .collect())
    }

    fn control(&self, id: u32) -> io::Result<i64> {
        match self.device.control(id)?.value {
            Value::Integer(v) => Ok(v),
            Value::Boolean(b) => Ok(i64::from(b)),
            other => Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!("control {id:#x} is not a number ({other:?})"),
            )),
        }
    }

    fn set_control(&mut self, control: &ControlInfo, value: i64) -> io::Result<()> {
        let value = match control.kind {
            ControlKind::Boolean => Value::Boolean(value != 0),
            _ => Value::Integer(value),
        };
        self.device.set_control(Control {
            id: control.id,
            value,
        })
    }

    fn start(&mut self, buffers: u32) -> io::Result<()> {
        if let Some(old) = self.stream.take() {
            Node::stop_stream(old)?;
        }
        let mut stream = Stream::with_buffers(&self.device, Type::VideoCapture, buffers)?;
        // Streaming starts now, not at the first dequeue: the crate's `next` queues the
        // buffer it handed out last (index 0 before the first), so queue the others and
        // stream on; the first `next` queues buffer 0. A device that allocated fewer
        // buffers than asked stops the loop at the first index it does not have.
        for index in 1..buffers as usize {
            match CaptureStream::queue(&mut stream, index) {
                Ok(()) => {}
                Err(e) if index >= 2 && e.kind() == io::ErrorKind::InvalidInput => break,
                Err(e) => return Err(e),
            }
        }
        stream.start()?;
        self.stream = Some(stream);
        Ok(())
    }

    fn dequeue(&mut self, timeout: Duration) -> io::Result<(&[u8], BufferMeta)> {
        let stream = self
            .stream
            .as_mut()
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotConnected, "not streaming"))?;
        // Whole milliseconds (rounded up), within poll's range.
        let ms = timeout.as_nanos().div_ceil(1_000_000).min(i32::MAX as u128) as u64;
        stream.set_timeout(Duration::from_millis(ms));
        let (data, meta) = CaptureStream::next(stream)?;
        let arrival = monotonic_now();
        let flags = meta.flags;
        let timestamp = Duration::new(
            u64::try_from(meta.timestamp.sec).unwrap_or(0),
            u32::try_from(meta.timestamp.usec.clamp(0, 999_999) * 1000).unwrap_or(0),
        );
        Ok((
            data,
            BufferMeta {
                sequence: meta.sequence,
                timestamp,
                monotonic: flags & BufferFlags::TIMESTAMP_MASK == BufferFlags::TIMESTAMP_MONOTONIC,
                source: if flags & BufferFlags::TSTAMP_SRC_MASK == BufferFlags::TSTAMP_SRC_SOE {
                    StampSource::StartOfExposure
                } else {
                    StampSource::EndOfFrame
                },
                bytes_used: meta.bytesused,
                error: flags.contains(BufferFlags::ERROR),
                arrival,
            },
        ))
    }

    fn stop(&mut self) -> io::Result<()> {
        match self.stream.take() {
            Some(stream) => Node::stop_stream(stream),
            None => Ok(()),
        }
    }

    fn now(&self) -> Duration {
        monotonic_now()
    }
}

/// `CLOCK_MONOTONIC`, the clock of V4L2's monotonic buffer timestamps.
fn monotonic_now() -> Duration {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid timespec to write; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

impl Drop for Node {
    fn drop(&mut self) {
        if let Some(stream) = self.stream.take() {
            // Best effort: the device may be gone already.
            let _ = Node::stop_stream(stream);
        }
    }
}
