//! The fill's scratch records — one per treelet, in id order: the raw treelet encoding (header
//! and used node records), then `used × bpv` attribute bytes — written once by the fill and read
//! back once per stream by the store pass, with direct I/O where the file system allows it.
//!
//! Why not through the page cache: the records are 3.5 GB at 10⁸ points, written once and read
//! back a few seconds later. Through the page cache every byte lands in a newly allocated page,
//! and on the virtual machines Arbor is measured on a page the guest touches for the first time
//! costs the host a fault: `dd` of 3 GB took 4.7 s buffered, all of it system time, against
//! 1.4 s and 0.3 s of system time with `O_DIRECT`, and reading a file back that is not cached
//! costs the same again. The records' copy into the page cache was 30 % of the 10⁸ fill's CPU
//! samples. With `O_DIRECT` the bytes move between a reused aligned buffer and the device.
//! Where the file system refuses `O_DIRECT` (tmpfs), the same code runs buffered.
//!
//! Offsets and lengths of direct I/O are whole pages: the writer keeps the unaligned tail of what
//! it has written for the next write and pads the last page with zeros; readers read whole pages
//! around the records they want. Where each record starts is a scratch column.

use std::fs::File;
use std::io;
use std::ops::Range;
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::path::Path;

use bytemuck::{Pod, Zeroable};

use crate::source::{Column, scratch_file};

/// Alignment of direct I/O: buffers, file offsets and lengths.
pub const PAGE: usize = 4096;

/// Bytes gathered before one write.
const WRITE_BYTES: usize = 1 << 20;

/// One page of an aligned buffer.
#[repr(C, align(4096))]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Page([u8; PAGE]);

/// A page-aligned byte buffer, grown on demand and reused.
#[derive(Default)]
pub struct AlignedBuf {
    pages: Vec<Page>,
}

impl AlignedBuf {
    /// The first `len` bytes rounded up to whole pages, growing the buffer if needed.
    fn pages_for(&mut self, len: usize) -> &mut [u8] {
        let n = len.div_ceil(PAGE);
        if self.pages.len() < n {
            self.pages.resize(n, Page::zeroed());
        }
        &mut bytemuck::cast_slice_mut(&mut self.pages)[..n * PAGE]
    }

    fn bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.pages)
    }

    fn bytes_mut(&mut self) -> &mut [u8] {
        bytemuck::cast_slice_mut(&mut self.pages)
    }
}

/// Creates (truncating) the scratch file at `path`, for direct I/O when `direct` is asked and
/// the file system allows it; returns whether it did.
fn create(path: &Path, direct: bool) -> io::Result<(File, bool)> {
    if !direct {
        return Ok((scratch_file(path)?, false));
    }
    let direct = File::options()
        .create(true)
        .truncate(true)
        .read(true)
        .write(true)
        .custom_flags(rustix::fs::OFlags::DIRECT.bits() as i32)
        .open(path);
    match direct {
        Ok(file) => Ok((file, true)),
        Err(e) if e.raw_os_error() == Some(rustix::io::Errno::INVAL.raw_os_error()) => {
            tracing::debug!(path = %path.display(), "direct I/O refused: scratch records buffered");
            Ok((scratch_file(path)?, false))
        }
        Err(e) => Err(e),
    }
}

/// A buffer of whole pages for the writer thread, and the file offset they go to.
type Pages = (AlignedBuf, usize, u64);

/// Appends records to the scratch file in whole pages, written by a thread of its own while the
/// next buffer fills (a direct write waits for the device; on the fill's own thread that wait
/// left a core idle).
pub struct RecordSink {
    direct: bool,
    buf: AlignedBuf,
    /// Bytes in `buf`; they belong at file offset `at`.
    len: usize,
    /// File offset of `buf`'s first byte (always a whole number of pages).
    at: u64,
    /// Full buffers to the writer thread.
    to_writer: Option<std::sync::mpsc::SyncSender<Pages>>,
    /// Written buffers back for reuse.
    written: std::sync::mpsc::Receiver<AlignedBuf>,
    writer: Option<std::thread::JoinHandle<io::Result<File>>>,
}

impl RecordSink {
    /// Creates the records file at `path`, written with direct I/O where the file system
    /// allows it.
    pub fn create(path: &Path) -> io::Result<Self> {
        Self::create_with(path, true)
    }

    /// [`RecordSink::create`], with direct I/O only if `direct` (false: through the page cache,
    /// as on a file system that refuses it).
    fn create_with(path: &Path, direct: bool) -> io::Result<Self> {
        let (file, direct) = create(path, direct)?;
        Self::with_file(file, direct)
    }

    /// A sink appending to `file` (opened for direct I/O if `direct`).
    fn with_file(file: File, direct: bool) -> io::Result<Self> {
        let (to_writer, full) = std::sync::mpsc::sync_channel::<Pages>(1);
        let (back, written) = std::sync::mpsc::channel::<AlignedBuf>();
        // Two buffers in turn: one filling, one being written.
        let mut spare = AlignedBuf::default();
        spare.pages_for(WRITE_BYTES + PAGE);
        let _ = back.send(spare);
        let writer = std::thread::Builder::new()
            .name("arbor-records".into())
            .spawn(move || {
                for (buf, len, at) in full {
                    file.write_all_at(&buf.bytes()[..len], at)?;
                    // Closed: the sink is finishing.
                    let _ = back.send(buf);
                }
                Ok(file)
            })?;
        let mut buf = AlignedBuf::default();
        buf.pages_for(WRITE_BYTES + PAGE);
        Ok(RecordSink {
            direct,
            buf,
            len: 0,
            at: 0,
            to_writer: Some(to_writer),
            written,
            writer: Some(writer),
        })
    }

    /// Bytes pushed so far: where the next record starts.
    pub fn position(&self) -> u64 {
        self.at + self.len as u64
    }

    /// Whether the file is written with direct I/O.
    pub fn direct(&self) -> bool {
        self.direct
    }

    /// Appends `bytes`.
    pub fn push(&mut self, bytes: &[u8]) -> io::Result<()> {
        let end = self.len + bytes.len();
        if end > self.buf.bytes().len() {
            self.buf.pages_for(end);
        }
        self.buf.bytes_mut()[self.len..end].copy_from_slice(bytes);
        self.len = end;
        if self.len >= WRITE_BYTES {
            self.write_pages()?;
        }
        Ok(())
    }

    /// Hands the whole pages gathered to the writer and keeps the partial last one.
    fn write_pages(&mut self) -> io::Result<()> {
        let whole = self.len / PAGE * PAGE;
        if whole == 0 {
            return Ok(());
        }
        let Ok(mut next) = self.written.recv() else {
            return Err(self.writer_error());
        };
        let tail = self.len - whole;
        next.pages_for(tail.max(WRITE_BYTES + PAGE))[..tail]
            .copy_from_slice(&self.buf.bytes()[whole..self.len]);
        let full = std::mem::replace(&mut self.buf, next);
        let sent = self
            .to_writer
            .as_ref()
            .map(|w| w.send((full, whole, self.at)));
        if !matches!(sent, Some(Ok(()))) {
            return Err(self.writer_error());
        }
        self.at += whole as u64;
        self.len = tail;
        Ok(())
    }

    /// Ends the writer thread once it has written what it was given: the file, or its error.
    fn stop_writer(&mut self) -> io::Result<File> {
        self.to_writer = None;
        match self.writer.take().map(|w| w.join()) {
            Some(Ok(result)) => result,
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            None => Err(io::Error::other("the scratch records' writer stopped")),
        }
    }

    /// The writer thread's error, once it has stopped.
    fn writer_error(&mut self) -> io::Error {
        match self.stop_writer() {
            Err(e) => e,
            Ok(_) => io::Error::other("the scratch records' writer stopped"),
        }
    }

    /// Writes what is left, its last page padded with zeros, and returns the file.
    pub fn finish(mut self) -> io::Result<File> {
        let padded = self.len.next_multiple_of(PAGE);
        self.buf.pages_for(padded);
        self.buf.bytes_mut()[self.len..padded].fill(0);
        self.len = padded;
        self.write_pages()?;
        self.stop_writer()
    }
}

/// The records file as the store pass reads it: ranges of records into a caller's buffer.
pub struct RecordFile {
    file: File,
    /// Attribute bytes per voxel.
    pub bpv: usize,
    /// Byte offset of every record, then the end.
    offsets: Column<u64>,
}

impl RecordFile {
    /// The records a [`RecordSink`] wrote to `file`, starting at `offsets`.
    pub fn open(file: File, bpv: usize, offsets: Column<u64>) -> Self {
        RecordFile { file, bpv, offsets }
    }

    /// Number of records.
    #[cfg(test)]
    pub fn count(&self) -> u32 {
        self.offsets.len().saturating_sub(1) as u32
    }

    /// Reads records `ids` into `buf`.
    pub fn read<'a>(&'a self, ids: Range<u32>, buf: &'a mut AlignedBuf) -> io::Result<Records<'a>> {
        let skip = self.read_into(ids.clone(), buf)?;
        Ok(self.view(ids, buf, skip))
    }

    /// Reads the whole pages around records `ids` into `buf`; returns where the first record
    /// starts in it.
    fn read_into(&self, ids: Range<u32>, buf: &mut AlignedBuf) -> io::Result<usize> {
        let (start, end) = (
            self.offsets[ids.start as usize],
            self.offsets[ids.end as usize],
        );
        let from = start / PAGE as u64 * PAGE as u64;
        let to = end.next_multiple_of(PAGE as u64);
        self.file
            .read_exact_at(buf.pages_for((to - from) as usize), from)?;
        Ok((start - from) as usize)
    }

    /// Records `ids` as [`RecordFile::read_into`] left them in `buf`.
    fn view<'a>(&'a self, ids: Range<u32>, buf: &'a AlignedBuf, skip: usize) -> Records<'a> {
        let offsets = &self.offsets[ids.start as usize..=ids.end as usize];
        let len = (offsets[offsets.len() - 1] - offsets[0]) as usize;
        Records {
            bytes: &buf.bytes()[skip..skip + len],
            base: offsets[0],
            offsets,
            first: ids.start,
            bpv: self.bpv,
        }
    }

    /// Calls `consume` with each of `ranges` in turn, read by a thread of its own up to
    /// [`READ_AHEAD`] ranges ahead: a direct read waits for the device, and waiting on the
    /// consumer's thread stalled the store pass (25–28 s against 20–22 s buffered at 10⁸).
    /// Stops at the first error, or when `consume` returns `false`.
    pub fn for_each<E: From<io::Error>>(
        &self,
        ranges: Vec<Range<u32>>,
        mut consume: impl FnMut(Range<u32>, Records<'_>) -> Result<bool, E>,
    ) -> Result<(), E> {
        type Read = io::Result<(Range<u32>, AlignedBuf, usize)>;
        std::thread::scope(|scope| {
            let (full_tx, full_rx) = std::sync::mpsc::sync_channel::<Read>(READ_AHEAD);
            let (empty_tx, empty_rx) = std::sync::mpsc::channel::<AlignedBuf>();
            for _ in 0..=READ_AHEAD {
                let _ = empty_tx.send(AlignedBuf::default());
            }
            scope.spawn(move || {
                for ids in ranges {
                    // Closed: the consumer stopped.
                    let Ok(mut buf) = empty_rx.recv() else { return };
                    let read = self.read_into(ids.clone(), &mut buf);
                    let failed = read.is_err();
                    if full_tx.send(read.map(|skip| (ids, buf, skip))).is_err() || failed {
                        return;
                    }
                }
            });
            for read in full_rx {
                let (ids, buf, skip) = read?;
                if !consume(ids.clone(), self.view(ids, &buf, skip))? {
                    break;
                }
                let _ = empty_tx.send(buf);
            }
            Ok(())
        })
    }
}

/// Ranges [`RecordFile::for_each`] reads ahead of its consumer (each buffer is reused).
const READ_AHEAD: usize = 2;

/// A range of records read by [`RecordFile::read`].
pub struct Records<'a> {
    bytes: &'a [u8],
    /// File offset of `bytes[0]`.
    base: u64,
    /// Offsets of the range's records, then its end.
    offsets: &'a [u64],
    /// Id of the range's first record.
    first: u32,
    bpv: usize,
}

impl Records<'_> {
    /// Byte range of record `id` in `bytes`, and where its attributes start.
    fn place(&self, id: u32) -> (usize, usize, usize) {
        let i = (id - self.first) as usize;
        let (start, end) = (self.offsets[i] - self.base, self.offsets[i + 1] - self.base);
        let header = arbor_proto::codec::HEADER_BYTES as u64;
        let used = (end - start - header) / (8 + self.bpv as u64);
        let attributes = start + header + used * 8;
        (start as usize, end as usize, attributes as usize)
    }

    /// A record's stored treelet encoding (header and used node records), final once filled.
    pub fn nodes(&self, id: u32) -> &[u8] {
        let (start, _, attributes) = self.place(id);
        &self.bytes[start..attributes]
    }

    /// A record's stored treelet encoding and its attribute bytes.
    pub fn record(&self, id: u32) -> (&[u8], &[u8]) {
        let (start, end, attributes) = self.place(id);
        (&self.bytes[start..attributes], &self.bytes[attributes..end])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::ColumnWriter;

    /// Records of every length around page boundaries, written through the sink and read back
    /// in ranges, equal what was written; the file is whole pages. Direct and buffered.
    #[test]
    fn records_cross_pages_and_read_back_exactly() {
        for direct in [true, false] {
            records_read_back(direct);
        }
    }

    /// A write that fails on the writer thread (here: a file opened read-only) is the error of
    /// the next push or of `finish`, not lost and not a hang.
    #[test]
    fn a_failed_write_is_the_next_push_or_finish_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r");
        std::fs::write(&path, b"").unwrap();
        let mut sink = RecordSink::with_file(File::open(&path).unwrap(), false).unwrap();
        let chunk = vec![7u8; 64 * 1024];
        let pushed = (0..64).try_for_each(|_| sink.push(&chunk));
        let err = match pushed {
            Err(e) => e,
            Ok(()) => sink.finish().unwrap_err(),
        };
        assert_eq!(
            err.raw_os_error(),
            Some(rustix::io::Errno::BADF.raw_os_error()),
            "{err}"
        );
    }

    /// The read-ahead thread hands ranges over in order, stops when the consumer says so, and
    /// a read that fails (records claimed past the file's end) is the consumer's error.
    #[test]
    fn reading_ahead_keeps_order_stops_when_told_and_reports_errors() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = RecordSink::create(&dir.path().join("r")).unwrap();
        let mut offsets = ColumnWriter::<u64>::create(dir.path(), "o").unwrap();
        offsets.push(0).unwrap();
        let header = arbor_proto::codec::HEADER_BYTES;
        for id in 0..100u32 {
            sink.push(&vec![id as u8; header + 3 * 9]).unwrap();
            offsets
                .push(u64::from(id + 1) * (header as u64 + 27))
                .unwrap();
        }
        let records = RecordFile::open(sink.finish().unwrap(), 1, offsets.finish().unwrap());
        let ranges: Vec<_> = (0..100).step_by(10).map(|s| s..s + 10).collect();
        let mut seen = Vec::new();
        records
            .for_each(ranges.clone(), |ids, r| {
                for id in ids.clone() {
                    assert!(r.nodes(id).iter().all(|&b| b == id as u8), "record {id}");
                }
                seen.push(ids.start);
                Ok::<_, io::Error>(ids.start < 30)
            })
            .unwrap();
        assert_eq!(seen, [0, 10, 20, 30]);
        let mut all = Vec::new();
        records
            .for_each(ranges, |ids, _| {
                all.push(ids.start);
                Ok::<_, io::Error>(true)
            })
            .unwrap();
        assert_eq!(all, (0..100).step_by(10).collect::<Vec<_>>());

        let mut claimed = ColumnWriter::<u64>::create(dir.path(), "past").unwrap();
        claimed.push(0).unwrap();
        claimed.push(1 << 16).unwrap();
        let file = File::open(dir.path().join("r")).unwrap();
        let past = RecordFile::open(file, 1, claimed.finish().unwrap());
        let err = past
            .for_each(std::iter::once(0..1).collect(), |_, _| {
                Ok::<_, io::Error>(true)
            })
            .unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::UnexpectedEof, "{err}");
    }

    fn records_read_back(direct: bool) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r");
        let mut sink = RecordSink::create_with(&path, direct).unwrap();
        if !direct {
            assert!(!sink.direct());
        }
        let mut offsets = ColumnWriter::<u64>::create(dir.path(), "o").unwrap();
        offsets.push(0).unwrap();
        let header = arbor_proto::codec::HEADER_BYTES;
        let bpv = 7;
        let mut written = Vec::new();
        let mut end = 0u64;
        let mut rng = arbor_proto::rng::SplitMix64::new(3);
        for id in 0..900u32 {
            let used = 1 + (rng.next_u64() % 600) as usize;
            let record: Vec<u8> = (0..header + used * (8 + bpv))
                .map(|k| (id as usize * 31 + k) as u8)
                .collect();
            sink.push(&record).unwrap();
            end += record.len() as u64;
            offsets.push(end).unwrap();
            written.push(record);
        }
        let file = sink.finish().unwrap();
        assert_eq!(
            file.metadata().unwrap().len(),
            end.next_multiple_of(PAGE as u64)
        );
        let records = RecordFile::open(file, bpv, offsets.finish().unwrap());
        assert_eq!(records.count(), 900);
        let mut buf = AlignedBuf::default();
        for range in [0..1, 0..900, 5..17, 899..900, 300..301, 512..899] {
            let read = records.read(range.clone(), &mut buf).unwrap();
            for id in range {
                let w = &written[id as usize];
                let (nodes, attrs) = read.record(id);
                assert_eq!(nodes.len() + attrs.len(), w.len(), "record {id}");
                assert_eq!([nodes, attrs].concat(), *w, "record {id}");
                assert_eq!(read.nodes(id), nodes);
                assert_eq!(attrs.len() % bpv, 0);
            }
        }
    }
}
