//! Reading and writing whole frames on a byte stream.
//!
//! The reader checks the header before allocating anything, reads the raw data part
//! straight into aligned words (small frames and the heads of big ones come through a buffer,
//! so a request costs one read from the socket rather than four), and gives a started frame a deadline to finish arriving, so a
//! slow or silent peer cannot hold memory or a task forever.

use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, BufReader, BufWriter};

use crate::frame::{Frame, FrameHeader, HEADER_LEN, HeaderError};

#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("connection closed")]
    Closed,
    #[error("connection closed in the middle of a frame")]
    Truncated,
    #[error("{0}")]
    Header(#[from] HeaderError),
    #[error("frame did not finish arriving within {0:?}")]
    Timeout(Duration),
    #[error("the peer was silent for {0:?} (no frame, not even a heartbeat)")]
    Silent(Duration),
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
}

/// Bytes read ahead from the stream: many small frames, or a big frame's head. A data part
/// longer than this is read straight into its words.
const READ_AHEAD: usize = 16 << 10;

pub struct FrameReader<R> {
    inner: BufReader<R>,
    /// Time a frame may take to arrive once its first byte has.
    pub frame_timeout: Duration,
    /// Time the peer may stay silent between frames (`None`: forever). Peers that send
    /// heartbeats set this to notice a peer that vanished without closing the connection.
    pub idle_deadline: Option<Duration>,
    /// Bytes read so far, for statistics.
    pub bytes_read: u64,
}

impl<R: AsyncRead + Unpin> FrameReader<R> {
    pub fn new(inner: R) -> FrameReader<R> {
        FrameReader {
            inner: BufReader::with_capacity(READ_AHEAD, inner),
            frame_timeout: Duration::from_secs(30),
            idle_deadline: None,
            bytes_read: 0,
        }
    }

    /// The next frame; `Closed` on a clean end of stream between frames.
    pub async fn read(&mut self) -> Result<Frame, ReadError> {
        let mut first = [0u8; 1];
        let n = match self.idle_deadline {
            Some(d) => tokio::time::timeout(d, self.inner.read(&mut first))
                .await
                .map_err(|_| ReadError::Silent(d))??,
            None => self.inner.read(&mut first).await?,
        };
        if n == 0 {
            return Err(ReadError::Closed);
        }
        let deadline = self.frame_timeout;
        match tokio::time::timeout(deadline, self.read_rest(first[0])).await {
            Ok(r) => r,
            Err(_) => Err(ReadError::Timeout(deadline)),
        }
    }

    async fn read_rest(&mut self, first: u8) -> Result<Frame, ReadError> {
        let mut hb = [0u8; HEADER_LEN];
        hb[0] = first;
        read_exact(&mut self.inner, &mut hb[1..]).await?;
        let header = FrameHeader::decode(&hb)?;
        let mut meta = vec![0u8; header.meta_len as usize];
        read_exact(&mut self.inner, &mut meta).await?;
        let mut data = vec![0u32; header.data_len as usize / 4].into_boxed_slice();
        read_exact(&mut self.inner, bytemuck::cast_slice_mut(&mut data)).await?;
        self.bytes_read += header.wire_len() as u64;
        Ok(Frame { header, meta, data })
    }
}

async fn read_exact<R: AsyncRead + Unpin>(r: &mut R, buf: &mut [u8]) -> Result<(), ReadError> {
    match r.read_exact(buf).await {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Err(ReadError::Truncated),
        Err(e) => Err(ReadError::Io(e)),
    }
}

/// Bytes of small frames gathered before they go to the stream together. A data part this
/// long or longer goes to the stream straight from the frame.
const WRITE_BEHIND: usize = 32 << 10;

/// Writes frames to a byte stream. Frames [`put`](FrameWriter::put) one after another are
/// gathered and reach the stream at the next [`flush`](FrameWriter::flush): on loopback each
/// write costs the sender the receiver's side of the stack as well, and a render node sending
/// a pixel row wrote twice (head, then data).
pub struct FrameWriter<W: AsyncWrite> {
    inner: BufWriter<W>,
    pub bytes_written: u64,
}

impl<W: AsyncWrite + Unpin> FrameWriter<W> {
    pub fn new(inner: W) -> FrameWriter<W> {
        FrameWriter {
            inner: BufWriter::with_capacity(WRITE_BEHIND, inner),
            bytes_written: 0,
        }
    }

    /// Writes `frame` and sends everything gathered.
    pub async fn write(&mut self, frame: &Frame) -> std::io::Result<()> {
        self.put(frame).await?;
        self.flush().await
    }

    /// Adds `frame` to what goes out at the next flush (a long data part may go at once).
    pub async fn put(&mut self, frame: &Frame) -> std::io::Result<()> {
        self.inner.write_all(&frame.header.encode()).await?;
        self.inner.write_all(&frame.meta).await?;
        if !frame.data.is_empty() {
            self.inner
                .write_all(bytemuck::cast_slice(&frame.data))
                .await?;
        }
        self.bytes_written += frame.wire_len() as u64;
        Ok(())
    }

    /// Sends every frame put so far.
    pub async fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush().await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::Message;

    #[tokio::test]
    async fn frames_cross_a_stream_whole() {
        let (a, b) = tokio::io::duplex(1 << 16);
        let mut w = FrameWriter::new(a);
        let mut r = FrameReader::new(b);
        let f = Frame::new(3, 9, &Message::Go, vec![1u32, 2, 3].into_boxed_slice()).with_tag(77);
        w.write(&f).await.unwrap();
        assert_eq!(r.read().await.unwrap(), f);
        drop(w);
        assert!(matches!(r.read().await, Err(ReadError::Closed)));
    }

    #[tokio::test]
    async fn oversized_length_is_refused_before_allocating() {
        let (mut a, b) = tokio::io::duplex(1 << 16);
        let mut hb = Frame::new(1, 2, &Message::Go, Box::new([])).header.encode();
        hb[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        a.write_all(&hb).await.unwrap();
        let mut r = FrameReader::new(b);
        assert!(matches!(
            r.read().await,
            Err(ReadError::Header(HeaderError::DataTooLarge(_)))
        ));
    }

    #[tokio::test]
    async fn a_stalled_frame_times_out() {
        let (mut a, b) = tokio::io::duplex(1 << 16);
        a.write_all(b"MAG").await.unwrap();
        let mut r = FrameReader::new(b);
        r.frame_timeout = Duration::from_millis(50);
        assert!(matches!(r.read().await, Err(ReadError::Timeout(_))));
    }

    #[tokio::test]
    async fn a_silent_peer_times_out_only_with_an_idle_deadline() {
        let (_a, b) = tokio::io::duplex(1 << 16);
        let mut r = FrameReader::new(b);
        assert!(
            tokio::time::timeout(Duration::from_millis(100), r.read())
                .await
                .is_err(),
            "without an idle deadline the reader waits"
        );
        r.idle_deadline = Some(Duration::from_millis(50));
        assert!(matches!(r.read().await, Err(ReadError::Silent(_))));
    }
}
