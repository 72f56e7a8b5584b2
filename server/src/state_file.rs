//! The state file (`esa-server --state-file PATH`): every live session, written when the server
//! stops gracefully and read when it starts, so that a restart or an upgrade continues every
//! session exactly where it was.
//!
//! The file holds what clients sent (their configs, actions and critic values), so it is treated
//! as a secret: it is written to a temporary file of mode 0600 beside it, synced and renamed over
//! it (a reader sees the old file or the whole new one, never a part), and a file that another
//! user owns, or that its group or others can write, is refused, as is a symbolic link. One
//! server at a time uses a path: a second one is refused while the first holds its lock file.
//!
//! Format: one header line, `esa-server state file, format 1, <N> bytes, crc32 <8 hex digits>`,
//! then N bytes of JSON ([`BodyIn`]). The header tells a foreign file from a truncated or corrupt
//! one, and a file of a newer format from this server's; every check fails with a message that
//! says which, and the server then does not start. Sessions are written and read one at a time,
//! so neither holds a second copy of every session in memory. A server loads the file once and
//! removes it before it serves, so a later crash cannot bring back state that clients have moved
//! past.

use std::cell::{Cell, RefCell};
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufRead as _, BufReader, BufWriter, Read, Seek as _, SeekFrom, Write};
use std::os::fd::AsRawFd as _;
use std::os::unix::fs::{MetadataExt as _, OpenOptionsExt as _};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use esa_core::{SavedSession, Session};
use serde::de::{self, SeqAccess, Visitor};
use serde::ser::{self, Serializer};
use serde::Deserialize as _;

use crate::error::StartError;
use crate::store::{Exported, SessionStore};

/// The format this server writes; it reads this one (and will read every older one).
pub const FORMAT: u32 = 1;

/// How every header starts.
const MAGIC: &str = "esa-server state file, format ";

/// Longest header line read before deciding that a file is not a state file.
const MAX_HEADER: u64 = 128;

/// One session of the file.
#[derive(Debug, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    id: String,
    /// Its idle time when the file was written.
    idle_nanos: u64,
    session: SavedSession,
}

/// What the JSON after the header holds, as it is written: the sessions come from an iterator.
#[derive(serde::Serialize)]
#[serde(bound = "I: Iterator<Item = Exported>")]
struct BodyOut<I> {
    written_by: &'static str,
    written_at_unix_nanos: u64,
    sessions: Streamed<I>,
}

/// What the JSON after the header holds, as it is read: each session restored as it comes.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct BodyIn {
    /// The esa-server version that wrote the file (for the log).
    written_by: String,
    /// When it was written, in nanoseconds since the Unix epoch: the downtime since then counts
    /// as idle time toward the sessions' TTL.
    written_at_unix_nanos: u64,
    sessions: Restored,
}

/// Sessions serialized from an iterator, once, counted.
struct Streamed<I> {
    sessions: RefCell<Option<I>>,
    count: Cell<usize>,
}

impl<I: Iterator<Item = Exported>> serde::Serialize for Streamed<I> {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let sessions = self
            .sessions
            .borrow_mut()
            .take()
            .ok_or_else(|| ser::Error::custom("the sessions were written already"))?;
        serializer.collect_seq(sessions.map(|exported| {
            self.count.set(self.count.get() + 1);
            Entry {
                id: exported.id,
                idle_nanos: u64::try_from(exported.idle.as_nanos()).unwrap_or(u64::MAX),
                session: exported.session,
            }
        }))
    }
}

/// The sessions of a file, each checked and restored as it is read: id, session, idle time when
/// the file was written.
#[derive(Debug)]
struct Restored(Vec<(String, Session, u64)>);

impl<'de> serde::Deserialize<'de> for Restored {
    fn deserialize<D: de::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Sessions;
        impl<'de> Visitor<'de> for Sessions {
            type Value = Restored;

            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a list of sessions")
            }

            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Restored, A::Error> {
                let mut restored = Vec::with_capacity(seq.size_hint().unwrap_or(0));
                while let Some(entry) = seq.next_element::<Entry>()? {
                    let session = Session::restore(entry.session).map_err(|err| {
                        de::Error::custom(format!("session {:?} is not valid: {err}", entry.id))
                    })?;
                    restored.push((entry.id, session, entry.idle_nanos));
                }
                Ok(Restored(restored))
            }
        }
        deserializer.deserialize_seq(Sessions)
    }
}

/// What a loaded file holds, checked: sessions ready to store, with their idle times.
#[derive(Debug)]
pub struct Loaded {
    /// The esa-server version that wrote the file.
    pub written_by: String,
    /// Each session's id, the session and its idle time now (downtime included).
    pub sessions: Vec<(String, Session, Duration)>,
}

/// What [`Loaded::restore_into`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RestoreCount {
    /// Sessions now live again.
    pub sessions: usize,
    /// Sessions idle past the TTL, not restored.
    pub expired: usize,
}

impl Loaded {
    /// Stores every session into `store`, except those idle past its TTL. A session the store
    /// refuses (its limits) stops the start: the message names the flag to raise.
    pub fn restore_into(self, store: &SessionStore) -> Result<RestoreCount, StartError> {
        let mut count = RestoreCount {
            sessions: 0,
            expired: 0,
        };
        for (id, session, idle) in self.sessions {
            let stored = store.import(id.clone(), session, idle).map_err(|err| {
                StartError::Config(format!(
                    "--state-file: cannot restore session {id:?}: {err}"
                ))
            })?;
            if stored {
                count.sessions += 1;
            } else {
                count.expired += 1;
            }
        }
        Ok(count)
    }
}

/// The state file at one path, and the lock that keeps other servers off it.
#[derive(Debug)]
pub struct StateFile {
    path: PathBuf,
    /// Held (an exclusive `flock`) for as long as this value lives.
    _lock: File,
}

impl StateFile {
    /// Takes the path for this process: its lock file beside it (`.<name>.lock`, mode 0600) is
    /// locked until this value is dropped, so a second server on the same path is refused. Also
    /// checks now that [`save`](Self::save) will be able to write the file (its directory exists
    /// and this user may create files there), so that a misplaced path stops the start rather
    /// than losing the sessions at the stop.
    pub fn open(path: impl Into<PathBuf>) -> Result<Self, StartError> {
        let path = path.into();
        let lock_path = sibling(&path, "lock");
        let lock = OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(&lock_path)
            .map_err(|err| io_error(&path, "cannot write", &err))?;
        // SAFETY: flock reads only its arguments; the descriptor is open for the call.
        if unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            let err = io::Error::last_os_error();
            return Err(if err.raw_os_error() == Some(libc::EWOULDBLOCK) {
                StartError::Config(format!(
                    "--state-file {}: another esa-server uses it (it holds {}); nothing was \
                     started",
                    path.display(),
                    lock_path.display()
                ))
            } else {
                io_error(&path, "cannot lock", &err)
            });
        }
        let file = Self { path, _lock: lock };
        let temporary = file.temporary();
        let created = create_private(&temporary);
        let _ = fs::remove_file(&temporary);
        created.map_err(|err| file.error("cannot write", &err))?;
        Ok(file)
    }

    /// Where it lives.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads and checks the file: `None` when there is none (a first start).
    pub fn load(&self) -> Result<Option<Loaded>, StartError> {
        let file = match OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(&self.path)
        {
            Ok(file) => file,
            Err(err) if err.kind() == io::ErrorKind::NotFound => return Ok(None),
            Err(err) if err.raw_os_error() == Some(libc::ELOOP) => {
                return Err(self.refused("it is a symbolic link; name the file itself"))
            }
            Err(err) => return Err(self.error("cannot read", &err)),
        };
        let size = self.check_private(&file)?;
        let mut reader = BufReader::new(file);
        let mut header = Vec::new();
        (&mut reader)
            .take(MAX_HEADER)
            .read_until(b'\n', &mut header)
            .map_err(|err| self.error("cannot read", &err))?;
        let header = header
            .strip_suffix(b"\n")
            .and_then(|line| std::str::from_utf8(line).ok())
            .and_then(parse_header)
            .ok_or_else(|| self.foreign())?;
        let (format, length, crc) = header.fields;
        if format != FORMAT {
            return Err(self.invalid(&format!(
                "it has format {format}, and this esa-server {} reads format {FORMAT}: start \
                 the esa-server version that wrote it, or one that reads its format",
                env!("CARGO_PKG_VERSION")
            )));
        }
        let body = size.saturating_sub(header.bytes);
        if body < length {
            return Err(self.invalid(&format!(
                "it is truncated: {body} of its {length} bytes are there"
            )));
        }
        if body > length {
            return Err(self.invalid(&format!("it has {} bytes after its end", body - length)));
        }
        let mut checked = Checked::new(reader.take(length));
        let mut json = serde_json::Deserializer::from_reader(&mut checked);
        let parsed = BodyIn::deserialize(&mut json).and_then(|body| json.end().map(|()| body));
        // A corrupt file is first of all corrupt, whatever its damage made the JSON say.
        io::copy(&mut checked, &mut io::sink()).map_err(|err| self.error("cannot read", &err))?;
        if checked.bytes != length || checked.hasher.clone().finalize() != crc {
            return Err(self.invalid("it is corrupt: its checksum does not match its content"));
        }
        let body =
            parsed.map_err(|err| self.invalid(&format!("its content does not decode: {err}")))?;
        let downtime = unix_nanos().saturating_sub(body.written_at_unix_nanos);
        let sessions = body
            .sessions
            .0
            .into_iter()
            .map(|(id, session, idle)| {
                let idle = Duration::from_nanos(idle.saturating_add(downtime));
                (id, session, idle)
            })
            .collect();
        Ok(Some(Loaded {
            written_by: body.written_by,
            sessions,
        }))
    }

    /// Removes the file (after [`load`](Self::load), once the server is about to serve).
    pub fn remove(&self) -> Result<(), StartError> {
        match fs::remove_file(&self.path) {
            Ok(()) => Ok(()),
            Err(err) if err.kind() == io::ErrorKind::NotFound => Ok(()),
            Err(err) => Err(self.error("cannot remove the loaded", &err)),
        }
    }

    /// Writes `sessions` atomically (a temporary file of mode 0600, synced, renamed over the
    /// path, the directory synced); returns how many sessions and bytes it wrote.
    pub fn save(
        &self,
        sessions: impl Iterator<Item = Exported>,
    ) -> Result<(usize, u64), StartError> {
        let temporary = self.temporary();
        let written = write_file(&temporary, sessions)
            .and_then(|written| fs::rename(&temporary, &self.path).map(|()| written))
            .and_then(|written| sync_dir(self.directory()).map(|()| written));
        written.map_err(|err| {
            let _ = fs::remove_file(&temporary);
            self.error("cannot write", &err)
        })
    }

    fn directory(&self) -> &Path {
        directory(&self.path)
    }

    /// A temporary name beside the file, of this process.
    fn temporary(&self) -> PathBuf {
        sibling(&self.path, &format!("{}.tmp", std::process::id()))
    }

    /// Refuses a file that is not a regular file of this user that only this user can write;
    /// returns its size.
    fn check_private(&self, file: &File) -> Result<u64, StartError> {
        let meta = file
            .metadata()
            .map_err(|err| self.error("cannot read", &err))?;
        if !meta.is_file() {
            return Err(self.refused("it is not a regular file"));
        }
        // SAFETY: geteuid has no preconditions and cannot fail.
        let uid = unsafe { libc::geteuid() };
        if meta.uid() != uid {
            return Err(self.refused(&format!(
                "it belongs to uid {}, not to this server's uid {uid}",
                meta.uid()
            )));
        }
        let mode = meta.mode() & 0o777;
        if mode & 0o022 != 0 {
            return Err(self.refused(&format!(
                "others can write it (mode {mode:o}): chmod 600 it if its content is \
                 trustworthy"
            )));
        }
        Ok(meta.len())
    }

    fn foreign(&self) -> StartError {
        self.invalid("it is not an esa-server state file (its first line is not the header)")
    }

    fn invalid(&self, why: &str) -> StartError {
        StartError::Config(format!(
            "--state-file {}: {why}; nothing was started (move the file away to start \
             without the sessions it holds)",
            self.path.display()
        ))
    }

    fn refused(&self, why: &str) -> StartError {
        StartError::Config(format!(
            "--state-file {}: refused: {why}; nothing was started",
            self.path.display()
        ))
    }

    fn error(&self, what: &str, err: &io::Error) -> StartError {
        io_error(&self.path, what, err)
    }
}

fn io_error(path: &Path, what: &str, err: &io::Error) -> StartError {
    StartError::Io(io::Error::new(
        err.kind(),
        format!("--state-file: {what} state file {}: {err}", path.display()),
    ))
}

fn directory(path: &Path) -> &Path {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    }
}

/// `.<file name>.<suffix>` beside `path`.
fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let name = path
        .file_name()
        .map_or_else(|| "state".into(), |n| n.to_string_lossy());
    directory(path).join(format!(".{name}.{suffix}"))
}

/// A parsed header line: its fields and its length with the newline.
struct Header {
    fields: (u32, u64, u32),
    bytes: u64,
}

/// `esa-server state file, format F, N bytes, crc32 C` as (F, N, C).
fn parse_header(line: &str) -> Option<Header> {
    let rest = line.strip_prefix(MAGIC)?;
    let (format, rest) = rest.split_once(", ")?;
    let (length, crc) = rest.split_once(" bytes, crc32 ")?;
    if crc.len() != 8 || !length.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(Header {
        fields: (
            format.parse().ok()?,
            length.parse().ok()?,
            u32::from_str_radix(crc, 16).ok()?,
        ),
        bytes: line.len() as u64 + 1,
    })
}

/// The header line, its length field of fixed width so that it can be written again in place.
fn header(length: u64, crc: u32) -> String {
    format!("{MAGIC}{FORMAT}, {length:020} bytes, crc32 {crc:08x}\n")
}

/// Bytes and CRC-32 of what passes through.
struct Checked<T> {
    inner: T,
    hasher: crc32fast::Hasher,
    bytes: u64,
}

impl<T> Checked<T> {
    fn new(inner: T) -> Self {
        Self {
            inner,
            hasher: crc32fast::Hasher::new(),
            bytes: 0,
        }
    }

    fn passed(&mut self, data: &[u8]) {
        self.hasher.update(data);
        self.bytes += data.len() as u64;
    }
}

impl<R: Read> Read for Checked<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.passed(&buf[..n]);
        Ok(n)
    }
}

impl<W: Write> Write for Checked<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.passed(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// Writes the header (its numbers filled in once the body is written) and the sessions, one at
/// a time, into a new private file at `path`, synced to disk. A temporary file left by a
/// process of the same id (this pid's, after a crash) is replaced.
fn write_file(path: &Path, sessions: impl Iterator<Item = Exported>) -> io::Result<(usize, u64)> {
    match fs::remove_file(path) {
        Ok(()) => {}
        Err(err) if err.kind() == io::ErrorKind::NotFound => {}
        Err(err) => return Err(err),
    }
    let mut file = create_private(path)?;
    file.write_all(header(0, 0).as_bytes())?;
    let body = BodyOut {
        written_by: env!("CARGO_PKG_VERSION"),
        written_at_unix_nanos: unix_nanos(),
        sessions: Streamed {
            sessions: RefCell::new(Some(sessions)),
            count: Cell::new(0),
        },
    };
    let mut out = Checked::new(BufWriter::new(&mut file));
    serde_json::to_writer(&mut out, &body).map_err(io::Error::other)?;
    out.flush()?;
    let (crc, length) = (out.hasher.clone().finalize(), out.bytes);
    drop(out);
    file.seek(SeekFrom::Start(0))?;
    let line = header(length, crc);
    file.write_all(line.as_bytes())?;
    file.sync_all()?;
    Ok((body.sessions.count.get(), line.len() as u64 + length))
}

fn unix_nanos() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

/// A new file of mode 0600 at `path` (never an existing file, nor through a symbolic link).
fn create_private(path: &Path) -> io::Result<File> {
    OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
}

/// Syncs a directory, so that a rename in it survives a power loss.
fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;
    use esa_core::SessionConfig;

    #[test]
    fn doubles_survive_the_file_bit_for_bit() {
        let config = SessionConfig {
            action_low: vec![f64::MIN, -0.0],
            action_high: vec![f64::MAX, 5e-324],
            normalize_response: true,
            ..SessionConfig::new(2, 0.1 + 0.2, vec![1.0 / 3.0], vec![3.0], vec![1e-300])
        };
        let mut session = Session::new(config).unwrap();
        let mut out = Vec::new();
        session
            .probe(0, &[-0.0, 2.2e-308], &[0.7], true, &mut out)
            .unwrap();
        session.report(0, 1e300, None, &mut out).unwrap();
        session
            .probe(1, &[1e-310, -0.0], &[], false, &mut out)
            .unwrap();
        session.report(1, -1e-300, Some(0.1), &mut out).unwrap();
        let mut saved = session.save();
        saved.shift = vec![-0.0, 4e-320];
        let dir = tempfile::tempdir().unwrap();
        let file = StateFile::open(dir.path().join("state")).unwrap();
        let exported = Exported {
            id: "s".into(),
            session: saved.clone(),
            idle: Duration::from_nanos(7),
        };
        let (count, bytes) = file.save(std::iter::once(exported)).unwrap();
        assert_eq!(count, 1);
        assert_eq!(bytes, fs::metadata(file.path()).unwrap().len());
        let loaded = file.load().unwrap().unwrap();
        let [(id, restored, idle)] = <[_; 1]>::try_from(loaded.sessions).unwrap();
        assert_eq!(id, "s");
        assert!(idle >= Duration::from_nanos(7));
        let again = restored.save();
        assert_eq!(
            serde_json::to_string(&again).unwrap(),
            serde_json::to_string(&saved).unwrap()
        );
        assert_eq!(again.shift[0].to_bits(), (-0.0f64).to_bits());
        assert_eq!(again.config.dt.to_bits(), (0.1f64 + 0.2).to_bits());
    }

    #[test]
    fn one_server_at_a_time_uses_a_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state");
        let first = StateFile::open(&path).unwrap();
        let err = StateFile::open(&path).unwrap_err();
        assert!(
            err.to_string().contains("another esa-server uses it"),
            "{err}"
        );
        drop(first);
        assert!(StateFile::open(&path).is_ok());
    }

    #[test]
    fn headers_parse_only_when_whole() {
        let line = header(1542, 0x469d_47e4);
        let parsed = parse_header(line.trim_end()).unwrap();
        assert_eq!(parsed.fields, (FORMAT, 1542, 0x469d_47e4));
        assert_eq!(parsed.bytes, line.len() as u64);
        assert!(parse_header("esa-server state file, format 1, 3 bytes, crc32 00000000").is_some());
        for bad in [
            "",
            "esa-server state file, format 1",
            "esa-server state file, format x, 3 bytes, crc32 00000000",
            "esa-server state file, format 1, 3 bytes, crc32 0000000",
            "esa-server state file, format 1, -3 bytes, crc32 00000000",
            "esa-server state file, format 1, +3 bytes, crc32 00000000",
            "PK\u{3}\u{4}",
        ] {
            assert!(parse_header(bad).is_none(), "{bad}");
        }
    }
}
