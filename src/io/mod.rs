//! Scene readers and writers. Every error names the file and the record, line or element.
//!
//! | format | files | reader |
//! |---|---|---|
//! | Waymo Open Motion Dataset | `*.tfrecord`, `*.tfrecord-00000-of-01000`, a directory of shards | [`womd`] |
//! | CommonRoad 2018b / 2020a | `*.xml`, `*.xml.gz` | [`commonroad`] |
//! | Argoverse 2 motion forecasting | `scenario_*.parquet` (map JSON beside it) or its directory | [`av2`] |
//! | GPUDrive / Nocturne scenario JSON (WOMD converted) | `*.json` with top-level `objects` or `roads` | [`gpudrive`] |
//! | drivescript YAML | `*.yaml`, `*.yml` | [`yaml`] |
//!
//! Rollouts (simulated futures) are read and written as JSON by [`rollout`].

pub mod av2;
pub mod commonroad;
pub mod copies;
pub mod gpudrive;
pub mod json;
pub mod name;
pub mod rollout;
pub mod scene_output;
pub mod shard;
pub mod tfrecord;
pub mod womd;
pub mod womd_proto;
pub mod womd_wire;
pub mod yaml;

use std::path::{Path, PathBuf};

use crate::scene::{Scene, SceneError};

pub use name::hidden_char;

/// The formats a scene can be read from, for error messages.
pub const SUPPORTED_FORMATS: &str = "Waymo Open Motion Dataset TFRecord (.tfrecord, *.tfrecord-NNNNN-of-NNNNN), \
CommonRoad XML (.xml, .xml.gz), Argoverse 2 scenario (.parquet or its directory), \
GPUDrive/Nocturne scenario JSON (.json with top-level objects and roads), drivescript YAML (.yaml, .yml)";

/// Most time steps a scene may have (over 2.7 hours at 10 Hz): a corrupted step index must
/// not turn into a huge allocation.
pub const MAX_STEPS: usize = 100_000;
/// The most states (agents × steps) a scene may hold: 5 million, 280 MB in memory; 550 times
/// the largest CommonRoad NGSIM scene (54 agents × 167 steps) and 400 times a WOMD scenario
/// (128 agents × 91 steps). Checked before the states are allocated, so that a 46 KB file
/// cannot ask for gigabytes.
pub const MAX_STATES: usize = 5_000_000;

/// Refuses a scene of `agents` × `steps` states beyond [`MAX_STATES`], before allocating.
pub(crate) fn check_states(
    path: &Path,
    location: &str,
    agents: usize,
    steps: usize,
) -> Result<(), IoError> {
    match agents.checked_mul(steps) {
        Some(n) if n <= MAX_STATES => Ok(()),
        _ => Err(IoError::invalid(
            path,
            location,
            format!(
                "{agents} agents x {steps} steps is more states than a scene may hold ({MAX_STATES})"
            ),
        )),
    }
}

/// A path as an error shows it: on one line, control and invisible characters escaped, so
/// that a file named `a\nerror: all good.xml` cannot print a line of its own.
fn shown(path: &str) -> String {
    name::one_line(path)
}

/// Errors from reading or writing scenes and rollouts.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The file could not be opened or read.
    #[error("{}: {source}", shown(.path))]
    Read {
        /// The file.
        path: String,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file could not be written.
    #[error("{}: cannot write: {source}", shown(.path))]
    Write {
        /// The file.
        path: String,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The format cannot be told from the name.
    #[error("{}: unknown scene format; supported: {SUPPORTED_FORMATS}", shown(.path))]
    UnknownFormat {
        /// The file.
        path: String,
    },
    /// The content is malformed at a given place (the whole file where `location` is
    /// "file", which is then not said: "x.json: file: is empty" said "file" twice).
    #[error("{}: {}", shown(.path), located(location, message))]
    Invalid {
        /// The file.
        path: String,
        /// Record index, line and column, element or row.
        location: String,
        /// What is wrong.
        message: String,
    },
    /// A scenario id that cannot name output files (a path, a dot name, control characters).
    #[error("scenario id \"{id}\" cannot name an output file: {message}")]
    Name {
        /// The id, as read ([`name::shown`]).
        id: String,
        /// What is wrong.
        message: String,
    },
    /// A scene number past the last scene of a multi-scene source ([`load_scene`]).
    #[error("{}: scene {index}: the source holds only {count} scenes", shown(.path))]
    NoSuchScene {
        /// The source.
        path: String,
        /// The number asked for, from 0.
        index: usize,
        /// The scenes it holds.
        count: usize,
    },
    /// The content parsed but makes an inconsistent scene.
    #[error("{}: {location}: {error}", shown(.path))]
    Scene {
        /// The file.
        path: String,
        /// Which scene in the file.
        location: String,
        /// What is inconsistent (in the message, not a separate source: a chain printer would
        /// say it twice).
        error: SceneError,
    },
}

/// `location: message`, or the message alone where the location is the whole file.
fn located(location: &str, message: &str) -> String {
    if location == "file" {
        message.to_string()
    } else {
        format!("{location}: {message}")
    }
}

impl IoError {
    /// What is wrong, without the file's name: for errors of other modules that name the file
    /// themselves.
    pub fn reason(&self) -> String {
        match self {
            IoError::Read { source, .. } => source.to_string(),
            IoError::Write { source, .. } => format!("cannot write: {source}"),
            IoError::Invalid {
                location, message, ..
            } => located(location, message),
            other => other.to_string(),
        }
    }

    pub(crate) fn invalid(
        path: &Path,
        location: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        IoError::Invalid {
            path: path.display().to_string(),
            location: location.into(),
            message: message.into(),
        }
    }

    /// A file that could not be opened or read; a dangling symbolic link is said to be one
    /// (the OS says "No such file or directory" of a name `ls` lists).
    pub(crate) fn read(path: &Path, source: std::io::Error) -> Self {
        if source.kind() == std::io::ErrorKind::NotFound {
            if let Some(to) = dangling_link(path) {
                return IoError::invalid(
                    path,
                    "file",
                    format!("is a symbolic link to {to}, which does not exist"),
                );
            }
        }
        IoError::Read {
            path: path.display().to_string(),
            source,
        }
    }
}

/// A scene file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneFormat {
    /// Waymo Open Motion Dataset TFRecord.
    Womd,
    /// CommonRoad XML.
    CommonRoad,
    /// Argoverse 2 scenario.
    Av2,
    /// GPUDrive / Nocturne scenario JSON.
    Gpudrive,
    /// drivescript YAML.
    Yaml,
}

/// Tells the format of a scene source from its name (and, for directories, their content).
pub fn detect_format(path: &Path) -> Result<SceneFormat, IoError> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    if path.is_dir() {
        if av2::is_scenario_dir(path) {
            return Ok(SceneFormat::Av2);
        }
        if womd::is_shard_dir(path) {
            return Ok(SceneFormat::Womd);
        }
        // Not "unknown scene format": `d.yaml/` has a scene's name, and what is wrong is that
        // it is a directory.
        return Err(IoError::invalid(
            path,
            "file",
            "is a directory, but neither an AV2 scenario directory (a scenario_*.parquet and \
             its log_map_archive_*.json) nor a directory of WOMD shards",
        ));
    }
    // An empty `.json` was "unknown scene format": its content decides whether it is a scene.
    // (Other names are scenes by name, and their readers say they are empty.)
    if name.ends_with(".json") && std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.len() == 0)
    {
        return Err(IoError::invalid(
            path,
            "file",
            "is empty (0 bytes): not a scene",
        ));
    }
    // The extension decides first: `tfrecord-00000-of-01000_4.json` is JSON, not a shard.
    // JSON is also what AV2 maps, rollouts and reports are written in, so a `.json` is a
    // scene only by its content; other JSON goes on to the checks below (and is refused).
    if name.ends_with(".json") && gpudrive::is_scenario_file(path) {
        Ok(SceneFormat::Gpudrive)
    } else if name.ends_with(".xml") || name.ends_with(".xml.gz") {
        Ok(SceneFormat::CommonRoad)
    } else if name.ends_with(".parquet") {
        Ok(SceneFormat::Av2)
    } else if name.ends_with(".yaml") || name.ends_with(".yml") {
        Ok(SceneFormat::Yaml)
    } else if name.ends_with(".tfrecord") {
        Ok(SceneFormat::Womd)
    } else if womd::is_shard_name(&name) {
        // WOMD's own names (`training.tfrecord-00000-of-01000`) carry no extension: the
        // content tells a shard from a file of another kind named like one.
        match sniff(path) {
            Some(Content::TfRecord) | None => Ok(SceneFormat::Womd),
            Some(other) => Err(IoError::invalid(
                path,
                "file",
                format!(
                    "named like a WOMD shard, but its content is {}, not a TFRecord",
                    other.describe()
                ),
            )),
        }
    } else {
        // A `.json` that cannot be read comes here (its content decides): a link loop is
        // named as one, not as an unknown format.
        // A device or FIFO named like nothing (`/dev/zero`) is named as what it is; one named
        // like a scene is detected by its name above, and refused where it is read.
        match std::fs::metadata(path) {
            Err(e) if is_link_loop(&e) => Err(read_error(path, e)),
            Ok(m) if !m.is_file() => Err(not_regular(path)),
            // A rollout given as a scene was "unknown scene format" and a list of formats,
            // which left the user guessing what the file they named is.
            _ if name.ends_with(".json") && is_rollout_file(path) => Err(IoError::invalid(
                path,
                "file",
                "is a drivescript rollout (sampled trajectories), not a scene: give its scene \
                 and pass it with --rollout (render, cost) or --rollouts DIR (eval)",
            )),
            _ => Err(IoError::UnknownFormat {
                path: path.display().to_string(),
            }),
        }
    }
}

/// Whether a file begins as the rollouts drivescript writes do (`{"format":
/// "drivescript-rollout"`, the first key [`rollout::Rollout`] serialises).
pub(crate) fn is_rollout_file(path: &Path) -> bool {
    use std::io::Read;
    let Ok(f) = open_regular(path, u64::MAX, "a scene file") else {
        return false;
    };
    let mut head = Vec::new();
    if f.take(256).read_to_end(&mut head).is_err() {
        return false;
    }
    let head = String::from_utf8_lossy(&head);
    let head: String = head.chars().filter(|c| !c.is_whitespace()).collect();
    head.trim_start_matches('\u{feff}')
        .starts_with(&format!("{{\"format\":\"{}\"", rollout::FORMAT_TAG))
}

/// Whether opening a path failed because its symbolic links lead back to themselves.
fn is_link_loop(e: &std::io::Error) -> bool {
    #[cfg(unix)]
    {
        e.raw_os_error() == Some(libc::ELOOP)
    }
    #[cfg(not(unix))]
    {
        let _ = e;
        false
    }
}

/// The error for a path that cannot be opened or examined: a link loop in words ("Too many
/// levels of symbolic links" does not say that the file is a link to itself), else the system's.
/// Where `path` is a symbolic link that leads to nothing, what it points at (shown safely).
pub fn dangling_link(path: &Path) -> Option<String> {
    let link = std::fs::symlink_metadata(path).ok()?;
    if !link.file_type().is_symlink() || std::fs::metadata(path).is_ok() {
        return None;
    }
    let to = std::fs::read_link(path).ok()?;
    Some(name::terminal_safe(&to.display().to_string()))
}

pub(crate) fn read_error(path: &Path, e: std::io::Error) -> IoError {
    if is_link_loop(&e) {
        IoError::invalid(
            path,
            "file",
            "is a symbolic link loop (its links lead back to themselves, never to a file)",
        )
    } else {
        IoError::read(path, e)
    }
}

/// What a file's first bytes say it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Content {
    /// A TFRecord (its first length matches its checksum).
    TfRecord,
    /// gzip-compressed data.
    Gzip,
    /// A Parquet file.
    Parquet,
    /// JSON text.
    Json,
    /// XML text.
    Xml,
    /// Some other text.
    Text,
    /// Neither of the above, or empty.
    Unknown,
}

impl Content {
    /// The kind in words, for messages.
    pub fn describe(self) -> &'static str {
        match self {
            Content::TfRecord => "a TFRecord",
            Content::Gzip => "gzip-compressed (decompress it first)",
            Content::Parquet => "a Parquet file",
            Content::Json => "JSON text",
            Content::Xml => "XML text",
            Content::Text => "text",
            Content::Unknown => "unrecognised binary data (or empty)",
        }
    }
}

/// Reads a file's first bytes and says what it appears to be (`None` when it cannot be read:
/// the reader reports that).
pub fn sniff(path: &Path) -> Option<Content> {
    use std::io::Read;
    let mut head = [0u8; 16];
    let mut f = open_regular(path, u64::MAX, "a scene file").ok()?;
    let mut n = 0;
    while n < head.len() {
        match f.read(&mut head[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(_) => return None,
        }
    }
    Some(classify(&head[..n]))
}

fn classify(head: &[u8]) -> Content {
    if head.len() >= 12
        && u32::from_le_bytes(head[8..12].try_into().expect("4 bytes"))
            == tfrecord::masked_crc32c(&head[..8])
    {
        return Content::TfRecord;
    }
    if head.starts_with(&[0x1f, 0x8b]) {
        return Content::Gzip;
    }
    if head.starts_with(b"PAR1") {
        return Content::Parquet;
    }
    // The first byte past whitespace and a UTF-8 byte-order mark.
    let first = head
        .iter()
        .find(|b| !(b.is_ascii_whitespace() || [0xef, 0xbb, 0xbf].contains(*b)));
    match first {
        Some(b'{') | Some(b'[') => Content::Json,
        Some(b'<') => Content::Xml,
        Some(_)
            if head
                .iter()
                .all(|b| b.is_ascii_graphic() || b.is_ascii_whitespace()) =>
        {
            Content::Text
        }
        _ => Content::Unknown,
    }
}

/// Every scene of a source, each read on its own: a WOMD record that is not a valid scenario
/// is one error among the good records (which are kept), and a source that cannot be read at
/// all is a single error. Commands that go over many scenes report the errors, go on, and
/// exit non-zero at the end.
pub fn read_each(path: &Path, opts: &LoadOptions) -> Vec<Result<Scene, IoError>> {
    // A reader that panics on some input is a bug, but it must cost that source only, not a
    // whole directory run.
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        read_each_unguarded(path, opts)
    }))
    .unwrap_or_else(|payload| {
        vec![Err(IoError::invalid(
            path,
            "reader",
            internal_error(&*payload, "file"),
        ))]
    })
}

/// What to say of a panic caught while working on one input (`what`: "file", "scene"): its
/// message, and that it is a bug to report with that input.
pub fn internal_error(payload: &(dyn std::any::Any + Send), what: &str) -> String {
    let message = payload
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "a panic".into());
    format!("internal error: {message} (a bug in drivescript: please report it with this {what})")
}

fn read_each_unguarded(path: &Path, opts: &LoadOptions) -> Vec<Result<Scene, IoError>> {
    match detect_format(path) {
        Ok(SceneFormat::Womd) => {
            let records = if path.is_dir() {
                womd::read_shards(path).map(|it| it.collect::<Vec<_>>())
            } else {
                womd::read_file(path).map(|it| it.collect::<Vec<_>>())
            };
            records.unwrap_or_else(|e| vec![Err(e)])
        }
        Ok(_) => match load_scenes(path, opts) {
            Ok(scenes) => scenes.into_iter().map(Ok).collect(),
            Err(e) => vec![Err(e)],
        },
        Err(e) => vec![Err(e)],
    }
}

/// Options for readers of formats that do not say where history ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadOptions {
    /// Current step for CommonRoad scenes (which have no notion of one), clamped to the
    /// scene's length. Default 10: 1 s of history plus the current state at 10 Hz, as WOMD.
    pub commonroad_current_step: usize,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            commonroad_current_step: 10,
        }
    }
}

/// Reads every scene of a source (a WOMD file or shard directory may hold many).
pub fn load_scenes(path: &Path, opts: &LoadOptions) -> Result<Vec<Scene>, IoError> {
    match detect_format(path)? {
        SceneFormat::Womd if path.is_dir() => womd::read_shards(path)?.collect(),
        SceneFormat::Womd => womd::read_file(path)?.collect(),
        SceneFormat::CommonRoad => Ok(vec![commonroad::read(path, opts)?]),
        SceneFormat::Av2 => Ok(vec![av2::read(path)?]),
        SceneFormat::Gpudrive => Ok(vec![gpudrive::read(path)?]),
        SceneFormat::Yaml => Ok(vec![yaml::read(path)?]),
    }
}

/// Reads scene number `index` of a source (0 for single-scene formats).
pub fn load_scene(path: &Path, index: usize, opts: &LoadOptions) -> Result<Scene, IoError> {
    let fmt = detect_format(path)?;
    if fmt == SceneFormat::Womd {
        let mut iter: Box<dyn Iterator<Item = Result<Scene, IoError>>> = if path.is_dir() {
            Box::new(womd::read_shards(path)?)
        } else {
            Box::new(womd::read_file(path)?)
        };
        let mut count = 0;
        for scene in iter.by_ref() {
            if count == index {
                return scene;
            }
            scene?;
            count += 1;
        }
        return Err(IoError::NoSuchScene {
            path: path.display().to_string(),
            index,
            count,
        });
    }
    let mut scenes = load_scenes(path, opts)?;
    if index >= scenes.len() {
        return Err(IoError::NoSuchScene {
            path: path.display().to_string(),
            index,
            count: scenes.len(),
        });
    }
    Ok(scenes.swap_remove(index))
}

/// The scene sources under `path`: the path itself if it is a file or an AV2 / WOMD directory,
/// else every readable source found in it (recursively), sorted. Only regular files are read: a
/// FIFO, socket or device named like a scene is an error (reading it would block or never
/// end), and a directory reached twice (a symlink loop, or two links to one directory) is
/// walked once.
pub fn discover(path: &Path) -> Result<Vec<PathBuf>, IoError> {
    let meta = std::fs::metadata(path).map_err(|e| read_error(path, e))?;
    if !meta.is_dir() {
        if !meta.is_file() {
            return Err(not_regular(path));
        }
        return Ok(vec![path.to_path_buf()]);
    }
    if detect_format(path).is_ok() {
        return Ok(vec![path.to_path_buf()]);
    }
    let mut out = Vec::new();
    let mut seen = std::collections::HashSet::new();
    walk(path, &mut seen, &mut out)?;
    Ok(out)
}

/// The first five of `items` joined by commas, and how many more there are: for warnings that
/// name what they are about without growing with the file.
pub(crate) fn first_few(items: &[String]) -> String {
    let mut shown: Vec<&str> = items.iter().take(5).map(String::as_str).collect();
    let more = items.len().saturating_sub(5);
    let tail = format!("and {more} more");
    if more > 0 {
        shown.push(&tail);
    }
    shown.join(", ")
}

/// The warning that names [`crate::scene::lanes_turning_back`], if any do (the readers of
/// polylines given as they are: WOMD, GPUDrive, CommonRoad and YAML maps).
pub(crate) fn turning_back_warning(lanes: &[crate::scene::Lane]) -> Option<String> {
    let back = crate::scene::lanes_turning_back(lanes);
    if back.is_empty() {
        return None;
    }
    let named: Vec<String> = back
        .iter()
        .map(|(id, s, turn)| format!("{id} ({turn:.0}° at {s:.1} m)"))
        .collect();
    Some(format!(
        "lanes whose centre line turns back on itself (over {}° within a metre), \
         read as written, so their lengths and paths along them are wrong: {}",
        crate::scene::MAX_LANE_TURN,
        first_few(&named)
    ))
}

fn not_regular(path: &Path) -> IoError {
    IoError::invalid(
        path,
        "file",
        "not a regular file (a FIFO, socket or device): reading it could block forever",
    )
}

/// Names a file or directory however it is reached (through links, `..`), for walks that must
/// visit each directory once: its device and inode. Canonicalising the path instead took time
/// in the cube of the depth (each level resolves every component above it, one `lstat` at a
/// time): a scene 1,500 directories deep took 23 s to find.
pub(crate) fn file_id(path: &Path) -> std::io::Result<(u64, u64)> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let m = std::fs::metadata(path)?;
        Ok((m.dev(), m.ino()))
    }
    #[cfg(not(unix))]
    {
        use std::hash::{Hash, Hasher};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        std::fs::canonicalize(path)?.hash(&mut h);
        Ok((0, h.finish()))
    }
}

fn walk(
    dir: &Path,
    seen: &mut std::collections::HashSet<(u64, u64)>,
    out: &mut Vec<PathBuf>,
) -> Result<(), IoError> {
    let id = file_id(dir).map_err(|e| IoError::read(dir, e))?;
    if !seen.insert(id) {
        return Ok(());
    }
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| IoError::read(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for p in entries {
        let scene_like = matches!(
            detect_format(&p),
            Ok(SceneFormat::CommonRoad
                | SceneFormat::Yaml
                | SceneFormat::Womd
                | SceneFormat::Gpudrive)
        );
        let meta = match std::fs::metadata(&p) {
            Ok(m) => m,
            // A dangling link named like a scene is an error; anything else is not ours.
            Err(e) if scene_like => return Err(read_error(&p, e)),
            Err(_) => continue,
        };
        if meta.is_dir() {
            if detect_format(&p).is_ok() {
                out.push(p);
            } else {
                walk(&p, seen, out)?;
            }
        } else if scene_like {
            if !meta.is_file() {
                return Err(not_regular(&p));
            }
            out.push(p);
        }
    }
    Ok(())
}

/// The bytes of the files under `path` (the file itself, or every file below a directory), for
/// a throughput figure. Each directory is walked once and each file counted once, by their
/// canonical paths: a symlink loop inside an AV2 directory (`a -> .`, `b -> .`) made the walk
/// branch until the OS's link limit, 2^40 paths for two such links, and one link counted every
/// file 40 times. A directory that cannot be read is an error naming it, not 0 bytes.
pub fn bytes_under(path: &Path) -> Result<u64, IoError> {
    fn add(
        p: &Path,
        seen: &mut std::collections::HashSet<(u64, u64)>,
        total: &mut u64,
    ) -> Result<(), IoError> {
        let meta = match std::fs::metadata(p) {
            Ok(m) => m,
            // A dangling link, or one that leads back to itself, holds no bytes; a reader
            // that needs the file it names says so itself.
            Err(_) if std::fs::symlink_metadata(p).is_ok_and(|m| m.file_type().is_symlink()) => {
                return Ok(())
            }
            Err(e) => return Err(read_error(p, e)),
        };
        if !meta.is_file() && !meta.is_dir() {
            // A FIFO or device is no scene's bytes, and sizing it reads nothing.
            return Ok(());
        }
        let id = file_id(p).map_err(|e| IoError::read(p, e))?;
        if !seen.insert(id) {
            return Ok(());
        }
        if meta.is_file() {
            *total = total.saturating_add(meta.len());
            return Ok(());
        }
        for entry in std::fs::read_dir(p).map_err(|e| IoError::read(p, e))? {
            let entry = entry.map_err(|e| IoError::read(p, e))?;
            add(&entry.path(), seen, total)?;
        }
        Ok(())
    }
    let mut total = 0;
    add(path, &mut std::collections::HashSet::new(), &mut total)?;
    Ok(total)
}

/// `id` when it can start a file name inside an output directory: scene files are untrusted,
/// and an id such as `../../x` must not write outside the directory the user named.
pub fn output_stem(id: &str) -> Result<&str, IoError> {
    let bad = |message: &str| {
        Err(IoError::Name {
            id: name::shown(id),
            message: message.into(),
        })
    };
    if id.is_empty() {
        return bad("it is empty");
    }
    if id.len() > name::MAX_SCENARIO_ID_BYTES {
        return bad(&format!(
            "it is longer than {} bytes",
            name::MAX_SCENARIO_ID_BYTES
        ));
    }
    if id.starts_with('.') {
        return bad("it starts with a dot");
    }
    if let Some(c) = id.chars().find(|&c| c == '/' || c == '\\' || c == ':') {
        return bad(&format!("it contains {c:?}"));
    }
    if let Err(c) = name::check_name(id) {
        return bad(&format!("it contains {c}"));
    }
    Ok(id)
}

/// [`output_stem`] of the scenario id read from `source`, the error naming that file: "scenario
/// id \"a/b\" cannot name an output file" stopped a run over a directory of scenes without
/// saying which file holds it.
pub fn output_stem_in<'a>(id: &'a str, source: &Path) -> Result<&'a str, IoError> {
    output_stem(id).map_err(|e| IoError::invalid(source, "scenario_id", e.to_string()))
}

/// The output names claimed by the scenes of one run, so that two scenes with one name
/// neither overwrite each other's outputs nor are scored against the same rollouts.
#[derive(Debug, Default)]
pub struct OutputNames(std::collections::HashMap<String, PathBuf>);

impl OutputNames {
    /// Claims the output name of `scenario_id` (read from `source`): the name, or an error
    /// naming the source that claimed it first.
    pub fn claim(&mut self, scenario_id: &str, source: &Path) -> Result<String, IoError> {
        let stem = output_stem_in(scenario_id, source)?.to_string();
        if let Some(first) = self.0.get(&stem) {
            return Err(IoError::invalid(
                source,
                format!("scenario {scenario_id:?}"),
                format!(
                    "has the name of a scene already read from {}: the two would share \
                     outputs ({stem}_K.json), so it is left out (give one of them another id, \
                     `convert --id`)",
                    first.display()
                ),
            ));
        }
        self.0.insert(stem.clone(), source.to_path_buf());
        Ok(stem)
    }
}

/// Writes `bytes` to a temporary file beside `path` (its directory created if needed), named
/// for this process and thread so that concurrent writers never share one; returns its path.
fn write_beside(path: &Path, bytes: &[u8]) -> Result<PathBuf, IoError> {
    let err = |source| IoError::Write {
        path: path.display().to_string(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    make_dirs(&dir, path)?;
    sweep_dead_temporaries(&dir);
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    // The name cut so that the temporary's stays within the 255 bytes a file name may have: a
    // 245-byte output name, itself valid, was refused as "File name too long".
    let mut cut = name.len().min(TMP_NAME_PREFIX_BYTES);
    while !name.is_char_boundary(cut) {
        cut -= 1;
    }
    let tmp = dir.join(format!(
        ".{}.tmp{}-{:?}",
        &name[..cut],
        std::process::id(),
        std::thread::current().id()
    ));
    // Created, never opened through whatever is there: a link planted at this predictable
    // name (in a directory others can write to) would otherwise send the bytes to its
    // target. A leftover of ours, or such a link, is removed first (removing a link leaves its
    // target alone); one planted again in between makes the create fail, not follow it.
    match std::fs::symlink_metadata(&tmp) {
        Ok(m) if m.is_dir() => {
            return Err(IoError::invalid(
                &tmp,
                "temporary file",
                "is a directory: remove it",
            ))
        }
        Ok(_) => std::fs::remove_file(&tmp).map_err(err)?,
        Err(_) => {}
    }
    let f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .map_err(err)?;
    fill_temporary(f, &tmp, bytes).map_err(err)?;
    Ok(tmp)
}

/// Writes `bytes` into the temporary `tmp` through `f`, removing it when that fails: a full
/// disk left what was written of it, hidden, holding the space.
fn fill_temporary(mut f: impl std::io::Write, tmp: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let done = f.write_all(bytes).and_then(|()| f.flush());
    drop(f);
    if done.is_err() {
        let _ = std::fs::remove_file(tmp);
    }
    done
}

/// The most bytes of an output's name kept in its temporary's name (`.NAME.tmpPID-ThreadId(N)`,
/// at most 46 bytes more), so that the temporary's name fits in 255 bytes.
const TMP_NAME_PREFIX_BYTES: usize = 200;

/// Whether `name` is that of a temporary [`write_beside`] makes, and if so the process that
/// made it.
fn temporary_owner(name: &str) -> Option<u32> {
    let (_, rest) = name.strip_prefix('.')?.rsplit_once(".tmp")?;
    let (pid, thread) = rest.split_once('-')?;
    let n = thread.strip_prefix("ThreadId(")?.strip_suffix(')')?;
    if pid.is_empty() || n.is_empty() || !pid.bytes().chain(n.bytes()).all(|b| b.is_ascii_digit()) {
        return None;
    }
    pid.parse().ok()
}

/// Removes from `dir` the temporaries of [`write_beside`] whose process has died (a Ctrl-C or
/// a kill in the middle of a write left them, hidden, as large as the output), once per
/// directory per process: a run writing thousands of files into one directory lists it once.
fn sweep_dead_temporaries(dir: &Path) {
    use std::collections::HashSet;
    use std::sync::Mutex;
    static SWEPT: Mutex<Option<HashSet<PathBuf>>> = Mutex::new(None);
    let key = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
    {
        let mut swept = SWEPT.lock().unwrap_or_else(|p| p.into_inner());
        if !swept.get_or_insert_with(HashSet::new).insert(key) {
            return;
        }
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let me = std::process::id();
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name.to_str().and_then(temporary_owner) else {
            continue;
        };
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        if pid != me && !is_dir && !process_alive(pid) {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Whether process `pid` exists (it may belong to another user: then it exists too): whether
/// a temporary file named for it may still be written, or was left by a process that died.
pub(crate) fn process_alive(pid: u32) -> bool {
    #[cfg(unix)]
    {
        let Ok(pid) = libc::pid_t::try_from(pid) else {
            return false;
        };
        // SAFETY: signal 0 checks for the process without sending anything.
        let r = unsafe { libc::kill(pid, 0) };
        r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
    }
    #[cfg(not(unix))]
    {
        let _ = pid;
        true
    }
}

/// Writes `bytes` to `path` atomically: a temporary file beside it, then a rename. Only a new
/// path or a regular file is replaced so; a device or a FIFO (`/dev/null`, `/dev/stdout`, a
/// pipe, or a link to one) is written in place, as a shell's `>` would: renaming over
/// `/dev/null` would replace it for the whole machine. A directory is an error, and so is a
/// symbolic link to a file or to nothing ([`refuse_output_link`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let err = |source| IoError::Write {
        path: path.display().to_string(),
        source,
    };
    check_names_a_file(path)?;
    refuse_output_link(path, "file")?;
    if let Ok(meta) = std::fs::metadata(path) {
        if meta.is_dir() {
            return Err(IoError::invalid(
                path,
                "file",
                "is a directory: name a file to write",
            ));
        }
        refuse_socket(path, &meta, "file")?;
        if !meta.is_file() {
            use std::io::Write;
            let mut f = std::fs::OpenOptions::new()
                .write(true)
                .open(path)
                .map_err(err)?;
            return f.write_all(bytes).and_then(|()| f.flush()).map_err(err);
        }
    }
    let tmp = write_beside(path, bytes)?;
    std::fs::rename(&tmp, path).map_err(|source| {
        let _ = std::fs::remove_file(&tmp);
        IoError::Write {
            path: path.display().to_string(),
            source,
        }
    })
}

/// Writes the file that `make` writes at the path it is given (a writer that takes a path,
/// such as candle's safetensors `save`) to `path` as [`write_atomic`] writes bytes: it is made
/// in a private directory of the system's temporary directory, read back, and written. Given
/// the output path itself, or a name beside it that it renamed, such a writer replaced a FIFO
/// or `/dev/null` with a regular file and left its partial file on a full disk.
pub fn write_atomic_from<E: std::fmt::Display>(
    path: &Path,
    make: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), IoError> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    check_names_a_file(path)?;
    let err = |source| IoError::Write {
        path: path.display().to_string(),
        source,
    };
    let private = std::env::temp_dir().join(format!(
        "drivescript-{}-{}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    ));
    // Created, never reused: one left by a process of this id that died is removed first.
    let _ = std::fs::remove_dir_all(&private);
    std::fs::create_dir(&private).map_err(err)?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let made = private.join(name.chars().take(100).collect::<String>());
    // Errors here name the private file: a full temporary directory is not a full output's.
    let private_err = |source| IoError::Write {
        path: made.display().to_string(),
        source,
    };
    let bytes = make(&made)
        .map_err(|e| private_err(std::io::Error::other(e.to_string())))
        .and_then(|()| std::fs::read(&made).map_err(private_err));
    let _ = std::fs::remove_dir_all(&private);
    write_atomic(path, &bytes?)
}

/// Refuses an output path that is a symbolic link to a regular file, to nothing (dangling) or
/// to itself (named by `field` in the message): the rename that writes an output replaced the
/// link itself with a regular file, and an output replaces only a user's regular file. A link
/// to a device or a FIFO (`/dev/stdout` is one) passes: such a path is written in place.
fn refuse_output_link(path: &Path, field: &str) -> Result<(), IoError> {
    let is_link = std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink());
    if !is_link {
        return Ok(());
    }
    match std::fs::metadata(path) {
        Ok(m) if !m.is_file() => Ok(()),
        _ => {
            let to = std::fs::read_link(path)
                .map(|t| format!(" (to {})", name::one_line(&t.display().to_string())))
                .unwrap_or_default();
            Err(IoError::invalid(
                path,
                field,
                format!(
                    "is a symbolic link{to}: writing would replace the link with a file; name \
                     the file it leads to, or remove the link first"
                ),
            ))
        }
    }
}

/// Refuses an output path that is a socket (named by `field` in the message): it cannot be
/// opened as a file, and the OS says only "No such device or address".
fn refuse_socket(path: &Path, meta: &std::fs::Metadata, field: &str) -> Result<(), IoError> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if meta.file_type().is_socket() {
            return Err(IoError::invalid(
                path,
                field,
                "is a socket, which cannot be written as a file: name a file (or a device or \
                 pipe) to write",
            ));
        }
    }
    let _ = (path, meta, field);
    Ok(())
}

/// Refuses an output path with a `..` after a directory that does not exist (`new/../in.yaml`):
/// no check can tell what it names until that directory is made, and writing made it, so
/// the path then named the input itself, which was replaced.
fn check_no_parent_of_missing(path: &Path) -> Result<(), IoError> {
    let mut prefix = PathBuf::new();
    for c in path.components() {
        if c == std::path::Component::ParentDir
            && !prefix.as_os_str().is_empty()
            && !prefix.is_dir()
        {
            return Err(IoError::invalid(
                path,
                "file",
                format!(
                    "leaves {} with `..`, but there is no such directory: name the file \
                     without it",
                    prefix.display()
                ),
            ));
        }
        prefix.push(c);
    }
    Ok(())
}

/// Refuses an output path that ends in a separator (`x.svg/`): it names a directory, and the
/// OS's own answer, "Not a directory", names neither the path nor the slip.
fn check_names_a_file(path: &Path) -> Result<(), IoError> {
    check_no_parent_of_missing(path)?;
    let raw = path.as_os_str().as_encoded_bytes();
    if raw.len() > 1
        && raw
            .last()
            .is_some_and(|&b| std::path::is_separator(b as char))
    {
        return Err(IoError::invalid(
            path,
            "file",
            "ends in a path separator, which names a directory: name the file to write \
             without the trailing slash",
        ));
    }
    Ok(())
}

/// A serde error's message without the position serde writes into it (` at line 4 column
/// 31`), for messages that give that position themselves; other positions (where an
/// unclosed bracket opened, say) stay.
/// Rust's names of types, in what serde expected, are said in words: "invalid type: floating
/// point `1.5`, expected usize" named a type of the program, not what the file should hold.
pub(crate) fn without_position(message: &str, line: usize, column: usize) -> String {
    plain_types(&message.replacen(&format!(" at line {line} column {column}"), "", 1))
}

/// [`without_position`]'s words for serde's "expected <Rust type>", for any serde message.
pub(crate) fn plain_types(message: &str) -> String {
    const WORDS: &[(&str, &str)] = &[
        ("i8", "a whole number"),
        ("i16", "a whole number"),
        ("i32", "a whole number from -2147483648 to 2147483647"),
        (
            "i64",
            "a whole number from -9223372036854775808 to 9223372036854775807",
        ),
        ("u8", "a whole number from 0 to 255"),
        ("u16", "a whole number from 0 to 65535"),
        ("u32", "a whole number from 0 to 4294967295"),
        ("u64", "a whole number, 0 or more"),
        ("usize", "a whole number, 0 or more"),
        ("f32", "a number"),
        ("f64", "a number"),
        ("bool", "true or false"),
    ];
    // A number beyond 64 bits is "integer `18446744073709551616` as u128": the type serde
    // read it as, which says nothing to a user.
    let message = &message
        .replace("` as u128, expected ", "`, expected ")
        .replace("` as i128, expected ", "`, expected ");
    let Some(at) = message.rfind("expected ") else {
        return message.to_string();
    };
    let (head, rest) = message.split_at(at + "expected ".len());
    let word_end = rest
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(rest.len());
    let (word, tail) = rest.split_at(word_end);
    if let Some((_, words)) = WORDS.iter().find(|(rust, _)| *rust == word) {
        return format!("{head}{words}{tail}");
    }
    // "expected tuple struct RolloutState with 4 elements", "expected struct YamlRoad".
    if word == "tuple" || word == "struct" {
        let (kind, tail) = match tail.strip_prefix(" struct ") {
            Some(t) => ("list", t),
            None => ("mapping of fields", tail.trim_start()),
        };
        let name_end = tail
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(tail.len());
        let after = &tail[name_end..];
        return match after.strip_prefix(" with ") {
            Some(n) => format!("{head}a {kind} of {}", n.replacen("elements", "values", 1)),
            None => format!("{head}a {kind}{after}"),
        };
    }
    message.to_string()
}

/// Writes `bytes` to `path` only if nothing is there, atomically: the file appears complete or
/// not at all, and of several processes racing to create it exactly one succeeds. Returns
/// `false` (writing nothing) when the file already exists.
pub fn create_atomic(path: &Path, bytes: &[u8]) -> Result<bool, IoError> {
    let err = |source| IoError::Write {
        path: path.display().to_string(),
        source,
    };
    check_names_a_file(path)?;
    let tmp = write_beside(path, bytes)?;
    // A hard link, unlike a rename, never replaces what is there.
    let linked = std::fs::hard_link(&tmp, path);
    let _ = std::fs::remove_file(&tmp);
    match linked {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(false),
        Err(e) => Err(err(e)),
    }
}

/// Reads a whole text file (a YAML scene, an AV2 map, a rollout) within [`MAX_SCENE_BYTES`].
/// A leading byte-order mark (Windows editors write one) is dropped: parsers would report it
/// as an unexpected character nobody can see.
pub(crate) fn read_text(path: &Path) -> Result<String, IoError> {
    let text = String::from_utf8(read_maybe_gz(path)?)
        .map_err(|e| IoError::invalid(path, "file", format!("not UTF-8 text: {e}")))?;
    // An empty rollout was "EOF while parsing a value ... (the file ends early: it is cut
    // short)", as if it had been cut.
    if text.is_empty() {
        return Err(IoError::invalid(path, "file", "is empty (0 bytes)"));
    }
    Ok(match text.strip_prefix('\u{FEFF}') {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// Opens `path` for reading if it is a regular file of at most `max` bytes (`what` says what
/// the file is, for the error: "a cost script"), refusing anything else before reading a byte.
/// A FIFO would block forever (even opening it, which is why it is opened non-blocking and
/// checked on the open handle) and a device such as `/dev/zero` never ends; a directory is not
/// a file. Every file drivescript reads comes through here.
pub fn open_regular(path: &Path, max: u64, what: &str) -> Result<std::fs::File, IoError> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        // Without it, opening a FIFO waits for a writer; reading a regular file ignores it.
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path).map_err(|e| read_error(path, e))?;
    let meta = file.metadata().map_err(|e| IoError::read(path, e))?;
    if meta.is_dir() {
        return Err(IoError::invalid(
            path,
            "file",
            format!("is a directory, not {what}"),
        ));
    }
    if !meta.is_file() {
        return Err(not_regular(path));
    }
    if meta.len() > max {
        return Err(too_large(path, "holds", meta.len(), max, what));
    }
    Ok(file)
}

/// Reads the whole of `path` through [`open_regular`], at most `max` bytes even if the file
/// grows while it is read.
pub fn read_regular(path: &Path, max: u64, what: &str) -> Result<Vec<u8>, IoError> {
    use std::io::Read;
    let file = open_regular(path, max, what)?;
    let mut out = Vec::new();
    file.take(max.saturating_add(1))
        .read_to_end(&mut out)
        .map_err(|e| IoError::read(path, e))?;
    if out.len() as u64 > max {
        return Err(too_large(path, "grew to", out.len() as u64, max, what));
    }
    Ok(out)
}

/// [`read_regular`] for a text file: UTF-8, or an error naming the file and the byte. A leading
/// byte-order mark is dropped, as [`read_text`] drops it: a script, a batch file, a checkpoint
/// config or a merge shard saved by a Windows editor was refused for a character nobody sees
/// ("Unexpected '\u{FEFF}'", "expected value at line 1 column 1").
pub fn read_regular_text(path: &Path, max: u64, what: &str) -> Result<String, IoError> {
    let text = String::from_utf8(read_regular(path, max, what)?)
        .map_err(|e| IoError::invalid(path, "file", format!("not UTF-8 text: {e}")))?;
    Ok(match text.strip_prefix('\u{FEFF}') {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

fn too_large(path: &Path, verb: &str, len: u64, max: u64, what: &str) -> IoError {
    let size = |b: u64| {
        if b >= 10 << 20 {
            format!("{} MB", b >> 20)
        } else if b >= 10 << 10 {
            format!("{} KB", b >> 10)
        } else {
            format!("{b} bytes")
        }
    };
    // Read or inflated sizes stop one byte past the cap: only a stored size is worth giving.
    let actual = if verb == "holds" {
        format!(" ({})", size(len))
    } else {
        String::new()
    };
    IoError::invalid(
        path,
        "file",
        format!(
            "{verb} more than {}{actual}, the most for {what}: far beyond a real one, so it is \
             refused before it fills memory",
            size(max)
        ),
    )
}

/// Creates the output directory `dir` (and its parents), or says plainly why not: the OS's
/// own words are `File exists` for a device, a file or a dangling link in the way.
pub fn create_output_dir(dir: &Path) -> Result<(), IoError> {
    let what = match std::fs::symlink_metadata(dir) {
        Err(_) => None,
        Ok(m) if m.file_type().is_symlink() => match std::fs::metadata(dir) {
            Ok(t) if t.is_dir() => None,
            Ok(_) => Some("is a symbolic link to something that is not a directory".to_string()),
            Err(_) => Some(format!(
                "is a symbolic link to {}, which does not exist: create that directory or \
                 remove the link",
                std::fs::read_link(dir)
                    .map(|t| t.display().to_string())
                    .unwrap_or_else(|_| "?".into())
            )),
        },
        Ok(m) if m.is_dir() => None,
        Ok(m) if m.is_file() => Some("is a file, not a directory".to_string()),
        Ok(_) => Some("is a device, FIFO or socket, not a directory".to_string()),
    };
    if let Some(why) = what {
        return Err(IoError::invalid(dir, "output directory", why));
    }
    make_dirs(dir, dir)
}

/// Makes `dir` and its parents for the output `path`, naming the part of the path in the way
/// where one is not a directory: the OS said `File exists` or `Not a directory` of the whole
/// path (`-o scene.yaml/x.svg`), naming no culprit.
fn make_dirs(dir: &Path, path: &Path) -> Result<(), IoError> {
    std::fs::create_dir_all(dir).map_err(|source| {
        let blocker = dir.ancestors().find(|a| {
            !a.as_os_str().is_empty() && std::fs::symlink_metadata(a).is_ok() && !a.is_dir()
        });
        match blocker {
            Some(b) => {
                let what = match std::fs::symlink_metadata(b) {
                    Ok(m) if m.is_file() => "a file",
                    Ok(m) if m.file_type().is_symlink() => {
                        "a symbolic link to something that is not a directory"
                    }
                    _ => "a device, FIFO or socket",
                };
                IoError::invalid(
                    path,
                    "output",
                    format!(
                        "{} is {what}, not a directory, so nothing can be written under it",
                        b.display()
                    ),
                )
            }
            None => IoError::Write {
                path: path.display().to_string(),
                source,
            },
        }
    })
}

/// Refuses an output path that is one of the command's `inputs` (the same file by any name:
/// writing would replace what is being read), or a scene file inside an input directory.
/// `flag` names the output option in the message (`-o`, `--json`).
pub fn check_output_not_input(output: &Path, inputs: &[&Path], flag: &str) -> Result<(), IoError> {
    check_no_parent_of_missing(output)?;
    let Ok(out) = std::fs::canonicalize(output) else {
        // Nothing there yet: it cannot be an input.
        return Ok(());
    };
    for input in inputs {
        let Ok(inp) = std::fs::canonicalize(input) else {
            continue;
        };
        // Inside a directory read as one scene (AV2, WOMD shards) every file is an input;
        // inside a directory of scenes, every scene file is.
        let inside_scene_dir = inp.is_dir()
            && out != inp
            && out.starts_with(&inp)
            && (detect_format(&inp).is_ok() || detect_format(&out).is_ok());
        if out == inp || inside_scene_dir {
            return Err(IoError::invalid(
                output,
                flag,
                if out == inp {
                    format!(
                        "is the input itself ({}): writing would replace what is read; write \
                         to another file",
                        input.display()
                    )
                } else {
                    format!(
                        "is a scene file inside the input directory {}: writing would replace \
                         it; write to another file",
                        input.display()
                    )
                },
            ));
        }
    }
    Ok(())
}

/// Refuses to replace an existing regular file at `output` unless it is a JSON object with the
/// top-level `key` that the command writes (`what` names that kind of file): a previous run's
/// output may be replaced, anything else (a checkpoint's `config.json`, a rollout, a scene) is
/// someone's data. New paths, devices and pipes pass.
pub fn check_replaces_own_json(
    output: &Path,
    key: &str,
    what: &str,
    flag: &str,
) -> Result<(), IoError> {
    check_replaces_own(output, flag, what, |p| {
        read_regular(p, MAX_SCENE_BYTES, what)
            .ok()
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .is_some_and(|v| v.get(key).is_some())
    })
}

/// Refuses to replace an existing regular file at `output` (named by `flag` in the message)
/// unless `ours` says it holds what the command writes (`what` names that kind of file): an
/// earlier output of the same kind may be replaced, anything else (a user's YAML, a picture
/// of another format, a many-scenario TFRecord) is someone's data. New paths, devices and
/// pipes pass: [`write_atomic`] writes those in place, as a shell's `>` would.
pub fn check_replaces_own(
    output: &Path,
    flag: &str,
    what: &str,
    ours: impl FnOnce(&Path) -> bool,
) -> Result<(), IoError> {
    check_no_parent_of_missing(output)?;
    // Said before the command's work, as write_atomic would say it after.
    refuse_output_link(output, flag)?;
    match std::fs::metadata(output) {
        Ok(m) if m.is_file() => {}
        // A directory too: `eval --json DIR` ran the whole evaluation and failed writing it.
        Ok(m) if m.is_dir() => {
            return Err(IoError::invalid(
                output,
                flag,
                "is a directory: name a file to write",
            ))
        }
        // Said before the command's work, not when its output is written.
        Ok(m) => return refuse_socket(output, &m, flag),
        Err(_) => return Ok(()),
    }
    if ours(output) {
        return Ok(());
    }
    Err(IoError::invalid(
        output,
        flag,
        format!(
            "already exists and is not {what}: writing would replace it; remove it first or \
             write to another file"
        ),
    ))
}

/// Reads a whole scene file, transparently gunzipping `.gz` files, within [`MAX_SCENE_BYTES`]
/// before and after inflating (NGSIM's largest CommonRoad file is 2.6 MB, an AV2 map a few
/// MB).
pub(crate) fn read_maybe_gz(path: &Path) -> Result<Vec<u8>, IoError> {
    use std::io::Read;
    const WHAT: &str = "a scene file";
    let raw = read_regular(path, MAX_SCENE_BYTES, WHAT)?;
    if path.extension().is_some_and(|e| e == "gz") {
        if !raw.starts_with(&[0x1f, 0x8b]) {
            return Err(not_gzip(path, &raw));
        }
        let mut out = Vec::new();
        // Inflated as a stream, at most one byte past the cap: a small file can inflate to
        // gigabytes. Every member: `cat a.gz b.gz` (and pigz, bgzip) make valid multi-member
        // files, of which a single-member decoder reads the first alone. Member by member
        // rather than with a multi-member decoder, which takes junk after the last member for
        // a damaged next one ("invalid gzip header", "unexpected end of file").
        let mut rest = &raw[..];
        while !rest.is_empty() {
            let at = raw.len() - rest.len();
            if !rest.starts_with(&[0x1f, 0x8b]) {
                return Err(IoError::invalid(
                    path,
                    "file",
                    format!(
                        "{} bytes of trailing data after the gzip stream (which ends at byte \
                         {at}): the file is damaged or was appended to",
                        rest.len()
                    ),
                ));
            }
            let mut member = flate2::bufread::GzDecoder::new(rest);
            (&mut member)
                .take(MAX_SCENE_BYTES + 1 - out.len() as u64)
                .read_to_end(&mut out)
                .map_err(|e| {
                    let place = if at == 0 {
                        "gzip stream".to_string()
                    } else {
                        format!("gzip member at byte {at}")
                    };
                    IoError::invalid(path, place, gzip_damage(&e, rest.len()))
                })?;
            if out.len() as u64 > MAX_SCENE_BYTES {
                break;
            }
            rest = member.into_inner();
        }
        if out.len() as u64 > MAX_SCENE_BYTES {
            return Err(too_large(
                path,
                "inflates to",
                out.len() as u64,
                MAX_SCENE_BYTES,
                WHAT,
            ));
        }
        Ok(out)
    } else {
        Ok(raw)
    }
}

/// What is wrong with a gzip stream of `len` bytes that the decoder refused with `e`, in words
/// that say the file is damaged: the decoder's own "unexpected end of file" or "incomplete
/// deflate stream" do not say that the file was cut short (an interrupted download or copy),
/// nor "corrupt deflate stream" that it cannot be read.
fn gzip_damage(e: &std::io::Error, len: usize) -> String {
    let text = e.to_string();
    if e.kind() == std::io::ErrorKind::UnexpectedEof || text.contains("incomplete") {
        format!(
            "truncated: its {len} bytes end before the gzip stream does ({text}): the file was \
             cut short, e.g. by an interrupted download or copy; fetch or compress it again"
        )
    } else {
        format!(
            "damaged gzip stream ({text}): the compressed data cannot be read back; fetch or \
             compress the file again"
        )
    }
}

/// The error for a `.gz` file that is not gzip-compressed: what it is instead, how it starts,
/// and the name to give it (a plain XML file named `.xml.gz` is a common slip, and "invalid
/// gzip header" does not say so).
fn not_gzip(path: &Path, raw: &[u8]) -> IoError {
    if raw.is_empty() {
        return IoError::invalid(path, "file", "is empty: not gzip-compressed");
    }
    let head = &raw[..raw.len().min(16)];
    let kind = classify(head);
    let start = match kind {
        Content::Json | Content::Xml | Content::Text => {
            // Its first line, at most 16 bytes of it: enough to recognise.
            let text = String::from_utf8_lossy(&raw[..raw.len().min(16)]);
            let line = text.trim_start().lines().next().unwrap_or("").trim_end();
            format!(" (starts with `{}`)", name::shown(line))
        }
        _ => String::new(),
    };
    let rename = path
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_suffix(".gz"))
        .filter(|n| matches!(kind, Content::Xml | Content::Json | Content::Text) && !n.is_empty())
        .map(|n| format!(": rename it to {}", name::shown(n)))
        .unwrap_or_default();
    IoError::invalid(
        path,
        "file",
        format!(
            "not gzip-compressed, it is {}{start}{rename}",
            kind.describe()
        ),
    )
}

/// The largest scene or rollout file (plain or inflated) a reader takes, in bytes: CommonRoad,
/// YAML, AV2 maps and parquets, rollout JSON. (WOMD files are read record by record, each
/// within [`tfrecord::MAX_RECORD_BYTES`].)
pub const MAX_SCENE_BYTES: u64 = 64 << 20;

/// The file name without extensions, as a fallback scenario id.
pub(crate) fn file_stem(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    name.split('.').next().unwrap_or(&name).to_string()
}

/// Adds a painted line unless the same line (either direction) is already there: formats store
/// the line between two lanes once per lane.
pub(crate) fn push_unique_road_line(
    lines: &mut Vec<crate::scene::RoadLine>,
    ends: &mut RoadLineEnds,
    line: crate::scene::RoadLine,
) {
    let (a, b) = (line.line.first(), line.line.last());
    let dup = ends.near(a).any(|i| {
        let l = &lines[i];
        let (p, q) = (l.line.first(), l.line.last());
        ((p - a).norm() < ROAD_LINE_SAME && (q - b).norm() < ROAD_LINE_SAME)
            || ((p - b).norm() < ROAD_LINE_SAME && (q - a).norm() < ROAD_LINE_SAME)
    });
    if !dup {
        ends.add(lines.len(), a, b);
        lines.push(line);
    }
}

/// Metres within which two road lines' ends are the same ([`push_unique_road_line`]).
const ROAD_LINE_SAME: f64 = 1e-3;

/// The road lines of a list by the cells (of [`ROAD_LINE_SAME`]) their end points fall in, for
/// [`push_unique_road_line`]: comparing each new line with every line kept made a map of a
/// few hundred thousand marked bounds take minutes.
pub(crate) struct RoadLineEnds(crate::geom::CellIndex);

impl RoadLineEnds {
    /// The ends of `lines`, as pushed one by one.
    pub(crate) fn of(lines: &[crate::scene::RoadLine]) -> Self {
        let mut ends = Self(crate::geom::CellIndex::new(ROAD_LINE_SAME, 1));
        for (i, l) in lines.iter().enumerate() {
            ends.add(i, l.line.first(), l.line.last());
        }
        ends
    }

    fn add(&mut self, i: usize, a: crate::geom::Point, b: crate::geom::Point) {
        self.0.insert(i, a, a);
        self.0.insert(i, b, b);
    }

    /// Lines with an end within [`ROAD_LINE_SAME`] of `p`, and some farther.
    fn near(&self, p: crate::geom::Point) -> impl Iterator<Item = usize> + '_ {
        self.0.around(p)
    }
}

#[cfg(test)]
mod tests {
    use super::{load_scenes, output_stem, without_position, LoadOptions};

    #[test]
    fn serde_s_names_of_rust_types_are_said_in_words() {
        for (serde, want) in [
            (
                "invalid type: floating point `1.5`, expected usize at line 2 column 15",
                "invalid type: floating point `1.5`, expected a whole number, 0 or more",
            ),
            (
                "invalid type: string \"x\", expected f64 at line 2 column 15",
                "invalid type: string \"x\", expected a number",
            ),
            (
                "invalid value: integer `9223372036854775808`, expected i64 at line 2 column 15",
                "invalid value: integer `9223372036854775808`, expected a whole number from \
                 -9223372036854775808 to 9223372036854775807",
            ),
            (
                "invalid length 0, expected tuple struct RolloutState with 4 elements at line 2 column 15",
                "invalid length 0, expected a list of 4 values",
            ),
            (
                "invalid type: integer `5`, expected struct YamlRoad at line 2 column 15",
                "invalid type: integer `5`, expected a mapping of fields",
            ),
            (
                "invalid type: integer `5`, expected a sequence at line 2 column 15",
                "invalid type: integer `5`, expected a sequence",
            ),
            (
                "invalid type: string \"u\", expected u8s at line 2 column 15",
                "invalid type: string \"u\", expected u8s",
            ),
            // A whole number beyond 64 bits: serde says the Rust type it read it as.
            (
                "invalid type: integer `18446744073709551616` as u128, expected usize at line 2 column 15",
                "invalid type: integer `18446744073709551616`, expected a whole number, 0 or more",
            ),
            (
                "invalid type: integer `-9223372036854775809` as i128, expected u32 at line 2 column 15",
                "invalid type: integer `-9223372036854775809`, expected a whole number from 0 to 4294967295",
            ),
        ] {
            assert_eq!(without_position(serde, 2, 15), want);
        }
    }

    #[test]
    fn an_output_path_with_a_trailing_slash_is_named_not_a_bare_os_error() {
        let dir = tempfile::tempdir().unwrap();
        for existing in [false, true] {
            let file = dir.path().join("x.svg");
            if existing {
                std::fs::write(&file, "<svg/>").unwrap();
            }
            let slashed = format!("{}/", file.display());
            let e = super::write_atomic(std::path::Path::new(&slashed), b"<svg/>")
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with(&slashed) && e.contains("trailing slash"),
                "{e}"
            );
        }
        // Nothing was written beside it, and the file of before is as it was.
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
        assert_eq!(
            std::fs::read_to_string(dir.path().join("x.svg")).unwrap(),
            "<svg/>"
        );
    }

    /// A thread reading `fifo` to its end: left running if the FIFO is replaced (then nobody
    /// ever writes to it).
    #[cfg(unix)]
    fn fifo_reader(fifo: &std::path::Path) -> std::thread::JoinHandle<String> {
        use std::io::Read;
        let f = fifo.to_path_buf();
        std::thread::spawn(move || {
            let mut t = String::new();
            std::fs::File::open(&f)
                .unwrap()
                .read_to_string(&mut t)
                .unwrap();
            t
        })
    }

    #[cfg(unix)]
    #[test]
    fn only_regular_files_within_their_cap_are_read() {
        use super::read_regular;
        let dir = tempfile::tempdir().unwrap();
        let e = read_regular(std::path::Path::new("/dev/zero"), 1 << 20, "a prompt")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("/dev/zero: not a regular file"), "{e}");
        // Whatever reads it as a scene (`bench io --womd /dev/zero`) says the same.
        let e = super::detect_format(std::path::Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("/dev/zero: not a regular file"), "{e}");
        let e = read_regular(dir.path(), 1 << 20, "a prompt")
            .unwrap_err()
            .to_string();
        assert!(e.contains("is a directory, not a prompt"), "{e}");
        let big = dir.path().join("big.md");
        std::fs::write(&big, vec![b'x'; 3000]).unwrap();
        let e = read_regular(&big, 2048, "a prompt")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("big.md: holds more than 2048 bytes (3000 bytes), the most for a prompt"),
            "{e}"
        );
        assert_eq!(read_regular(&big, 3000, "a prompt").unwrap().len(), 3000);
        let fifo = dir.path().join("f");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if made.is_ok_and(|s| s.success()) {
            // Opening alone would block without a writer.
            let e = read_regular(&fifo, 1 << 20, "a prompt")
                .unwrap_err()
                .to_string();
            assert!(e.contains("not a regular file"), "{e}");
        }
    }

    #[test]
    fn a_dot_dot_after_a_directory_that_does_not_exist_is_refused_not_resolved_by_writing() {
        // `convert in.yaml -o new/../in.yaml` made `new` and replaced in.yaml, exit 0.
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.yaml");
        std::fs::write(&input, "# mine\n").unwrap();
        let sneaky = dir.path().join("new/../in.yaml");
        super::check_output_not_input(&sneaky, &[&input], "-o").unwrap_err();
        let e = super::check_replaces_own(&sneaky, "-o", "a YAML scene", |_| true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("leaves") && e.contains("new with `..`, but there is no such directory"),
            "{e}"
        );
        super::write_atomic(&sneaky, b"x").unwrap_err();
        assert!(!super::create_atomic(&sneaky, b"x").unwrap_or(false));
        assert_eq!(std::fs::read_to_string(&input).unwrap(), "# mine\n");
        assert!(!dir.path().join("new").exists());
        // Through a directory that exists, `..` is as the OS resolves it.
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        super::write_atomic(&dir.path().join("sub/../out.yaml"), b"x").unwrap();
        assert!(dir.path().join("out.yaml").exists());
    }

    #[cfg(unix)]
    #[test]
    fn a_file_a_writer_makes_at_its_own_path_reaches_a_fifo_in_place() {
        // `bench sample --export FIFO` renamed its file over the FIFO (as root, over
        // /dev/null for the whole machine).
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("x.safetensors");
        super::write_atomic_from(&out, |p| std::fs::write(p, b"made")).unwrap();
        assert_eq!(std::fs::read(&out).unwrap(), b"made");
        let e = super::write_atomic_from(&out, |_| Err("no room"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("drivescript-") && e.contains("no room"), "{e}");
        assert_eq!(std::fs::read(&out).unwrap(), b"made");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
        let fifo = dir.path().join("f.safetensors");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        assert!(made.is_ok_and(|s| s.success()));
        let reader = fifo_reader(&fifo);
        super::write_atomic_from(&fifo, |p| std::fs::write(p, b"piped")).unwrap();
        let kind = std::fs::symlink_metadata(&fifo).unwrap().file_type();
        assert!(kind.is_fifo(), "the FIFO was replaced by {kind:?}");
        assert_eq!(reader.join().unwrap(), "piped");
    }

    #[test]
    fn a_write_that_fails_leaves_no_temporary_behind() {
        // A writer that takes 10 bytes and then finds the disk full.
        struct Full(usize);
        impl std::io::Write for Full {
            fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
                if self.0 >= 10 {
                    return Err(std::io::Error::from_raw_os_error(28));
                }
                let n = b.len().min(10 - self.0);
                self.0 += n;
                Ok(n)
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path().join(".x.json.tmp1-ThreadId(1)");
        std::fs::write(&tmp, b"0123456789").unwrap();
        assert!(super::fill_temporary(Full(0), &tmp, &[b'x'; 100]).is_err());
        assert!(!tmp.exists());
        std::fs::write(&tmp, b"").unwrap();
        super::fill_temporary(Full(0), &tmp, b"short").unwrap();
        assert!(tmp.exists());
    }

    #[test]
    fn an_output_name_near_the_longest_a_file_may_have_is_written() {
        // Its temporary's name, 30 bytes longer, was refused: "File name too long".
        let dir = tempfile::tempdir().unwrap();
        for name in ["a".repeat(250), format!("{}.json", "é".repeat(122))] {
            let out = dir.path().join(&name);
            super::write_atomic(&out, b"{}").unwrap();
            assert_eq!(std::fs::read(&out).unwrap(), b"{}");
            let other = format!("b{}", name.chars().skip(1).collect::<String>());
            assert!(super::create_atomic(&dir.path().join(other), b"{}").unwrap());
        }
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(names.iter().all(|n| !n.starts_with('.')), "{names:?}");
    }

    #[test]
    fn temporaries_of_writers_that_died_are_removed_and_no_others() {
        // A kill in the middle of a write left `.NAME.tmpPID-ThreadId(N)` for good.
        let dir = tempfile::tempdir().unwrap();
        let dead = dir.path().join(".old.gif.tmp4000000001-ThreadId(3)");
        let live = dir.path().join(".old.gif.tmp1-ThreadId(1)");
        let mine = [
            ".notes.tmp",
            ".a.tmp12-ThreadId(x)",
            ".b.tmp-ThreadId(1)",
            "c.tmp5-ThreadId(1)",
        ];
        for p in [&dead, &live] {
            std::fs::write(p, b"partial").unwrap();
        }
        for n in mine {
            std::fs::write(dir.path().join(n), b"mine").unwrap();
        }
        super::write_atomic(&dir.path().join("new.json"), b"{}").unwrap();
        assert!(!dead.exists());
        assert!(live.exists());
        for n in mine {
            assert!(dir.path().join(n).exists(), "{n}");
        }
        assert_eq!(super::temporary_owner(".x.tmp77-ThreadId(2)"), Some(77));
        assert_eq!(super::temporary_owner(".x.tmp77-ThreadId()"), None);
    }

    #[cfg(unix)]
    #[test]
    fn a_socket_as_output_is_named_as_such_before_and_at_the_write() {
        let dir = tempfile::tempdir().unwrap();
        let sock = dir.path().join("out.json");
        let _listener = std::os::unix::net::UnixListener::bind(&sock).unwrap();
        let e = super::write_atomic(&sock, b"{}").unwrap_err().to_string();
        assert!(e.contains("out.json: is a socket"), "{e}");
        let e = super::check_replaces_own_json(&sock, "table", "an eval table", "--json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("out.json: --json: is a socket"), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn a_link_planted_at_the_temporary_name_is_not_written_through() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim");
        std::fs::write(&victim, b"keep").unwrap();
        let out = dir.path().join("out.json");
        let tmp = dir.path().join(format!(
            ".out.json.tmp{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        std::os::unix::fs::symlink(&victim, &tmp).unwrap();
        super::write_atomic(&out, b"new").unwrap();
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
        assert_eq!(std::fs::read(&out).unwrap(), b"new");
        assert!(!tmp.exists() && std::fs::symlink_metadata(&tmp).is_err());
    }

    #[cfg(unix)]
    #[test]
    fn a_fifo_output_is_written_in_place_and_a_directory_is_refused() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let e = super::write_atomic(dir.path(), b"x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("is a directory"), "{e}");
        let fifo = dir.path().join("out.json");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if !made.is_ok_and(|s| s.success()) {
            return;
        }
        let reader = fifo_reader(&fifo);
        super::write_atomic(&fifo, b"{\"a\": 1}").unwrap();
        let kind = std::fs::symlink_metadata(&fifo).unwrap().file_type();
        assert!(kind.is_fifo(), "the FIFO was replaced by {kind:?}");
        assert_eq!(reader.join().unwrap(), "{\"a\": 1}");
    }

    #[test]
    fn multi_member_gzip_and_a_byte_order_mark_are_read_whole() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/samples");
        let xml = std::fs::read(root.join("commonroad/USA_US101-3_3_T-1.xml")).unwrap();
        // Two gzip members, as `cat a.gz b.gz` makes.
        let mut gz = Vec::new();
        for half in [&xml[..xml.len() / 2], &xml[xml.len() / 2..]] {
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            e.write_all(half).unwrap();
            gz.extend(e.finish().unwrap());
        }
        let p = dir.path().join("two.xml.gz");
        std::fs::write(&p, gz).unwrap();
        assert_eq!(super::read_maybe_gz(&p).unwrap(), xml);
        let yaml = std::fs::read(root.join("yaml/highway_cut_in.yaml")).unwrap();
        let p = dir.path().join("bom.yaml");
        std::fs::write(&p, [&b"\xEF\xBB\xBF"[..], &yaml].concat()).unwrap();
        let plain = super::yaml::read(&root.join("yaml/highway_cut_in.yaml")).unwrap();
        let bom = super::yaml::read(&p).unwrap();
        assert_eq!(bom.meta.scenario_id, plain.meta.scenario_id);
        assert_eq!(bom.agents.len(), plain.agents.len());
        // Every other text file drivescript reads (scripts, batch files, configs) too.
        let p = dir.path().join("bom.json");
        std::fs::write(&p, b"\xEF\xBB\xBF{\"a\": 1}").unwrap();
        assert_eq!(
            super::read_regular_text(&p, 100, "a test file").unwrap(),
            "{\"a\": 1}"
        );
    }

    #[test]
    fn a_plain_file_named_gz_and_junk_after_the_stream_are_named_as_such() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/samples");
        let xml = std::fs::read(root.join("commonroad/USA_US101-3_3_T-1.xml")).unwrap();
        let p = dir.path().join("plain.xml.gz");
        std::fs::write(&p, &xml).unwrap();
        let e = super::read_maybe_gz(&p).unwrap_err().to_string();
        assert!(
            e.contains("plain.xml.gz: not gzip-compressed, it is XML text")
                && e.contains("(starts with `<commonRoad")
                && e.contains("rename it to plain.xml"),
            "{e}"
        );
        let p = dir.path().join("empty.xml.gz");
        std::fs::write(&p, b"").unwrap();
        let e = super::read_maybe_gz(&p).unwrap_err().to_string();
        assert!(e.contains("empty.xml.gz: is empty"), "{e}");

        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(&xml).unwrap();
        let gz = enc.finish().unwrap();
        // Short junk (which a multi-member decoder calls "unexpected end of file") and long
        // junk ("invalid gzip header").
        for junk in [&b"junk\n"[..], &[0u8; 100][..]] {
            let p = dir.path().join("junk.xml.gz");
            std::fs::write(&p, [&gz[..], junk].concat()).unwrap();
            let e = super::read_maybe_gz(&p).unwrap_err().to_string();
            assert!(
                e.contains(&format!(
                    "junk.xml.gz: {} bytes of trailing data after the gzip stream (which \
                     ends at byte {})",
                    junk.len(),
                    gz.len()
                )),
                "{e}"
            );
        }
        // A damaged second member is named by its place.
        let p = dir.path().join("second.xml.gz");
        std::fs::write(&p, [&gz[..], &gz[..20]].concat()).unwrap();
        let e = super::read_maybe_gz(&p).unwrap_err().to_string();
        assert!(
            e.contains(&format!("second.xml.gz: gzip member at byte {}", gz.len())),
            "{e}"
        );
    }

    #[test]
    fn a_truncated_or_corrupt_gzip_file_is_named_as_such() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/samples");
        let xml = std::fs::read(root.join("commonroad/USA_US101-3_3_T-1.xml")).unwrap();
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(&xml).unwrap();
        let gz = enc.finish().unwrap();
        // Cut in the header, in the deflate data and in the trailer (the decoder says
        // "unexpected end of file" for some, "incomplete deflate stream" for others).
        for keep in [
            6,
            15,
            gz.len() / 2,
            gz.len() - 100,
            gz.len() - 4,
            gz.len() - 1,
        ] {
            let p = dir.path().join("cut.xml.gz");
            std::fs::write(&p, &gz[..keep]).unwrap();
            let e = super::read_maybe_gz(&p).unwrap_err().to_string();
            assert!(
                e.contains("cut.xml.gz: gzip stream: truncated: ")
                    && e.contains(&format!("its {keep} bytes end before the gzip stream does"))
                    && e.contains("interrupted download or copy"),
                "{keep}: {e}"
            );
        }
        // A changed byte in the data, and in the checksum.
        for at in [gz.len() / 2, gz.len() - 6] {
            let mut bad = gz.clone();
            bad[at] ^= 0xff;
            let p = dir.path().join("bad.json.gz");
            std::fs::write(&p, &bad).unwrap();
            let e = super::read_maybe_gz(&p).unwrap_err().to_string();
            assert!(
                e.contains("bad.json.gz: gzip stream: damaged gzip stream (")
                    && e.contains("cannot be read back"),
                "{at}: {e}"
            );
        }
        // A rollout or YAML scene compressed the same way says the same.
        let p = dir.path().join("cut.yaml.gz");
        std::fs::write(&p, &gz[..gz.len() / 2]).unwrap();
        let e = super::read_text(&p).unwrap_err().to_string();
        assert!(e.contains("cut.yaml.gz: gzip stream: truncated"), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn an_output_name_that_is_a_link_to_a_file_or_to_nothing_is_left_alone() {
        let dir = tempfile::tempdir().unwrap();
        let earlier = dir.path().join("earlier.json");
        std::fs::write(&earlier, "{\"format\": 1}").unwrap();
        let link = dir.path().join("out.json");
        std::os::unix::fs::symlink(&earlier, &link).unwrap();
        let dangling = dir.path().join("gone.json");
        std::os::unix::fs::symlink(dir.path().join("nowhere"), &dangling).unwrap();
        for (p, to) in [(&link, &earlier), (&dangling, &dir.path().join("nowhere"))] {
            let e = super::write_atomic(p, b"new").unwrap_err().to_string();
            assert!(
                e.contains(&format!("is a symbolic link (to {})", to.display()))
                    && e.contains("name the file it leads to"),
                "{e}"
            );
            let e = super::check_replaces_own(p, "-o", "a rollout", |_| true)
                .unwrap_err()
                .to_string();
            assert!(e.contains("-o: is a symbolic link"), "{e}");
            assert!(std::fs::symlink_metadata(p)
                .unwrap()
                .file_type()
                .is_symlink());
        }
        assert_eq!(
            std::fs::read_to_string(&earlier).unwrap(),
            "{\"format\": 1}"
        );
        // A link to a device is written through, as /dev/stdout is.
        let null = dir.path().join("null");
        std::os::unix::fs::symlink("/dev/null", &null).unwrap();
        super::write_atomic(&null, b"x").unwrap();
        assert!(std::fs::symlink_metadata(&null)
            .unwrap()
            .file_type()
            .is_symlink());
        // The file it leads to is written as any regular file is.
        super::write_atomic(&earlier, b"new").unwrap();
        assert_eq!(std::fs::read(&earlier).unwrap(), b"new");
    }

    #[cfg(unix)]
    #[test]
    fn an_output_directory_in_the_way_is_named_for_what_it_is() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("dangling");
        std::os::unix::fs::symlink(dir.path().join("nowhere"), &link).unwrap();
        let e = super::create_output_dir(&link).unwrap_err().to_string();
        assert!(
            e.contains("is a symbolic link to") && e.contains("which does not exist"),
            "{e}"
        );
        let e = super::create_output_dir(std::path::Path::new("/dev/null"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("is a device, FIFO or socket, not a directory"),
            "{e}"
        );
        let f = dir.path().join("f");
        std::fs::write(&f, "x").unwrap();
        let e = super::create_output_dir(&f).unwrap_err().to_string();
        assert!(e.contains("is a file, not a directory"), "{e}");
        super::create_output_dir(&dir.path().join("a/b")).unwrap();
        super::create_output_dir(&dir.path().join("a/b")).unwrap();
    }

    #[test]
    fn serde_positions_are_said_once() {
        let e = serde_yaml::from_str::<serde_yaml::Value>("road: [1, 2").unwrap_err();
        let l = e.location().unwrap();
        assert_eq!(
            without_position(&e.to_string(), l.line(), l.column()),
            "did not find expected ',' or ']', while parsing a flow sequence at line 1 column 7"
        );
        let e = serde_json::from_str::<serde_json::Value>("{\"a\": }").unwrap_err();
        assert_eq!(
            without_position(&e.to_string(), e.line(), e.column()),
            "expected value"
        );
    }

    #[test]
    fn a_yaml_scene_error_gives_its_position_once() {
        let text = "scenario_id: x\ndt: 0.1\nroad: {lanes: 2, width: 3}\n";
        let e = super::yaml::parse(std::path::Path::new("s.yaml"), text)
            .unwrap_err()
            .to_string();
        assert_eq!(e.matches("line 3").count(), 1, "{e}");
        assert!(e.contains("unknown field `width`"), "{e}");
    }

    #[test]
    fn output_stems_are_single_plain_names() {
        for ok in ["USA_US101-3_3_T-1", "a1b2#3", "0a1e6f0a-uuid", "demo"] {
            assert_eq!(output_stem(ok).unwrap(), ok);
        }
        let long = "x".repeat(201);
        for (bad, why) in [
            ("", "empty"),
            ("../x", "starts with a dot"),
            ("a/../../b", "'/'"),
            ("a\\b", "'\\\\'"),
            ("C:x", "':'"),
            ("a\u{1b}[2Jb", "control character U+001B"),
            ("cut\u{202E}ni", "invisible character U+202E"),
            ("a\u{200B}b", "invisible character U+200B"),
            (long.as_str(), "longer than 200"),
        ] {
            let e = output_stem(bad).unwrap_err().to_string();
            assert!(e.contains(why), "{bad:?}: {e}");
        }
    }

    #[test]
    fn a_path_with_a_line_break_is_shown_on_one_line_in_every_error() {
        // Paths reached messages raw: a file named `a\nerror: all good.yaml` printed a line
        // of its own, an escape sequence in a name reached the terminal.
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("scene\nerror: all good\u{1b}[2J.yaml");
        std::fs::write(&bad, "agents: [").unwrap();
        let missing = dir.path().join("gone\nerror: all good.yaml");
        for path in [&bad, &missing] {
            let err = load_scenes(path, &LoadOptions::default())
                .unwrap_err()
                .to_string();
            assert!(!err.contains('\n') && !err.contains('\u{1b}'), "{err}");
            assert!(err.contains("\\u{000A}error: all good"), "{err}");
        }
    }
}
