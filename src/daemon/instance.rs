//! One edod per state directory and per socket.
//!
//! The first thing edod does is take two exclusive locks (`flock`), held until it
//! exits: `edod.lock` in the state directory and `<socket>.lock` beside the socket.
//! Each holds the holder's pid, socket and state directory. A second edod on the same
//! state directory or the same socket finds a lock taken and stops at once, naming the
//! running one, before it starts a simulator, reads or marks a job, or touches the
//! socket. The kernel drops a lock when its holder dies (even by SIGKILL), so a stale
//! lock file never blocks a restart.
//!
//! Files edod creates in the state directory get explicit modes, whatever the umask:
//! the lock files 0640 (the group may read who runs), the job database and its
//! `-wal`/`-shm` files 0600 (operators reach jobs through the API).
//!
//! Nothing there is followed or trusted blindly: the state directory and the socket's
//! directory must belong to edod's user (or root) and be writable by no other user
//! (no group or other write bit), and every file edod opens there is opened without
//! following a symbolic link (`O_NOFOLLOW`) and must belong to edod's user. What is
//! refused is named, before anything in it is read, written or chmod-ed.

use std::fs::File;
use std::io::{Read, Seek, Write};
use std::os::unix::fs::{DirBuilderExt, MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use nix::fcntl::{Flock, FlockArg};

use super::config::Config;

/// Mode of the lock files.
pub const LOCK_FILE_MODE: u32 = 0o640;
/// Mode of the job database and its `-wal` and `-shm` files.
pub const DB_FILE_MODE: u32 = 0o600;
/// Mode of a state directory edod creates.
pub const STATE_DIR_MODE: u32 = 0o750;
/// The job database's file name in the state directory.
pub const DB_FILE: &str = "edod.db";
/// The state directory's lock file.
pub const STATE_LOCK_FILE: &str = "edod.lock";

/// The locks a running edod holds; dropped (released) when it stops.
#[derive(Debug)]
pub struct InstanceLock {
    _state: Flock<File>,
    _socket: Flock<File>,
}

/// The lock file beside `socket`: `<socket>.lock`.
pub fn socket_lock_path(socket: &Path) -> PathBuf {
    let mut s = socket.as_os_str().to_owned();
    s.push(".lock");
    PathBuf::from(s)
}

/// Take the state directory's lock, then the socket's (creating the state directory,
/// mode 0750, and the socket's directory if they are missing); an error names the edod
/// that holds one. Nothing else is read or written before both are held.
pub fn lock(cfg: &Config) -> Result<InstanceLock> {
    let state_dir = &cfg.state.dir;
    create_dir(state_dir, STATE_DIR_MODE)
        .with_context(|| format!("cannot create state dir {}", state_dir.display()))?;
    check_dir(state_dir, "state dir ([state] dir)")?;
    let socket = &cfg.api.socket;
    if let Some(dir) = socket.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        check_dir(dir, "socket's directory ([api] socket)")?;
    }
    let holder = format!(
        "pid {}\nsocket {}\nstate {}\n",
        std::process::id(),
        socket.display(),
        state_dir.display()
    );
    let state = take(&state_dir.join(STATE_LOCK_FILE), &holder, "state directory")?;
    let socket = take(&socket_lock_path(socket), &holder, "socket")?;
    Ok(InstanceLock {
        _state: state,
        _socket: socket,
    })
}

/// Create `dir` (and its parents) with `mode` if it is missing.
fn create_dir(dir: &Path, mode: u32) -> std::io::Result<()> {
    if dir.is_dir() {
        return Ok(());
    }
    std::fs::DirBuilder::new()
        .recursive(true)
        .mode(mode)
        .create(dir)?;
    // The umask may have taken bits away; it cannot have added any.
    std::fs::set_permissions(dir, std::fs::Permissions::from_mode(mode))
}

/// `dir` belongs to edod's user or root and no other user can write in it: else another
/// user could plant a file or a link where edod writes. `what` names it in the error.
fn check_dir(dir: &Path, what: &str) -> Result<()> {
    let meta = std::fs::metadata(dir).with_context(|| format!("cannot read {}", dir.display()))?;
    let me = nix::unistd::geteuid().as_raw();
    if meta.uid() != me && meta.uid() != 0 {
        bail!(
            "the {what} {} belongs to uid {}, not to edod's user (uid {me}) or root:              refusing it (another user could replace what edod keeps there)",
            dir.display(),
            meta.uid()
        );
    }
    let mode = meta.mode() & 0o7777;
    if mode & 0o022 != 0 {
        bail!(
            "the {what} {} has mode {mode:04o}: other users can write in it; refusing              it (chmod go-w, or give edod a directory of its own)",
            dir.display()
        );
    }
    Ok(())
}

/// Open `path` in edod's state without following a symbolic link, and check it belongs
/// to edod's user: a link or another user's file planted there is refused, naming it,
/// before anything is written or chmod-ed.
fn open_own(path: &Path, options: &mut std::fs::OpenOptions, what: &str) -> Result<File> {
    let file = options
        .custom_flags(nix::libc::O_NOFOLLOW)
        .open(path)
        .map_err(|e| match e.raw_os_error() {
            Some(nix::libc::ELOOP) => anyhow::anyhow!(
                "{what} {} is a symbolic link: refusing to follow it (remove it)",
                path.display()
            ),
            _ => anyhow::Error::new(e).context(format!("cannot open {what} {}", path.display())),
        })?;
    let uid = file
        .metadata()
        .with_context(|| format!("cannot read {}", path.display()))?
        .uid();
    let me = nix::unistd::geteuid().as_raw();
    if uid != me {
        bail!(
            "{what} {} belongs to uid {uid}, not to edod's user (uid {me}): refusing it",
            path.display()
        );
    }
    Ok(file)
}

/// Lock `path` (created mode 0640) and write `holder` into it; `what` names it in the
/// error when another edod holds it.
fn take(path: &Path, holder: &str, what: &str) -> Result<Flock<File>> {
    let file = open_own(
        path,
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(LOCK_FILE_MODE),
        "the lock file",
    )?;
    set_mode(&file, path, LOCK_FILE_MODE)?;
    let mut lock = match Flock::lock(file, FlockArg::LockExclusiveNonblock) {
        Ok(l) => l,
        Err((mut file, nix::errno::Errno::EWOULDBLOCK)) => {
            bail!(
                "another edod ({}) is running with this {what} (lock {}); stop it first \
                 or give this one its own [state] dir and [api] socket",
                describe_holder(&mut file),
                path.display()
            )
        }
        Err((_, e)) => bail!("cannot lock {}: {e}", path.display()),
    };
    let written = lock
        .set_len(0)
        .and_then(|()| lock.rewind())
        .and_then(|()| lock.write_all(holder.as_bytes()))
        .and_then(|()| lock.sync_data());
    written.with_context(|| format!("cannot write {}", path.display()))?;
    Ok(lock)
}

/// Give `file` exactly `mode`, whatever the umask was when it was created.
fn set_mode(file: &File, path: &Path, mode: u32) -> Result<()> {
    file.set_permissions(std::fs::Permissions::from_mode(mode))
        .with_context(|| format!("cannot set the mode of {}", path.display()))
}

/// "pid N, socket S" from a lock file another edod holds. Its holder writes it right
/// after locking: wait a moment for a lock taken an instant ago.
fn describe_holder(file: &mut File) -> String {
    for _ in 0..20 {
        let mut text = String::new();
        if file.rewind().is_ok() && file.read_to_string(&mut text).is_ok() {
            let field = |key: &str| {
                text.lines()
                    .find_map(|l| l.strip_prefix(key).map(str::trim).map(str::to_string))
            };
            if let (Some(pid), Some(socket)) = (field("pid "), field("socket ")) {
                let state = field("state ").unwrap_or_default();
                return format!("pid {pid}, socket {socket}, state dir {state}");
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    "pid unknown".to_string()
}

/// Create the job database file (mode 0600) if it is missing, and give it and its
/// `-wal` and `-shm` files mode 0600 whatever the umask. SQLite creates the `-wal` and
/// `-shm` files with the database file's mode; call again after opening the store.
pub fn secure_db_files(state_dir: &Path) -> Result<()> {
    let db = state_dir.join(DB_FILE);
    let file = open_own(
        &db,
        std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(false)
            .mode(DB_FILE_MODE),
        "the job database",
    )?;
    set_mode(&file, &db, DB_FILE_MODE)?;
    for suffix in ["-wal", "-shm"] {
        let mut name = db.as_os_str().to_owned();
        name.push(suffix);
        let path = PathBuf::from(name);
        if path.symlink_metadata().is_ok() {
            let file = open_own(
                &path,
                std::fs::OpenOptions::new().read(true),
                "the job database's",
            )?;
            set_mode(&file, &path, DB_FILE_MODE)?;
        }
    }
    Ok(())
}

/// Descriptors edod holds besides its clients' connections: the store (the database,
/// its `-wal` and `-shm`, on its threads), the serial port or the simulator's pty, the
/// two locks, the listeners, the runtime's own (epoll, eventfds), a mesh file being
/// read, the journal's stream; with room to spare.
pub const OWN_DESCRIPTORS: u64 = 64;

/// The open files edod's connection budget needs: each client place on the socket
/// and, when the dashboard is served, as many again on it (counted apart), plus
/// [`OWN_DESCRIPTORS`].
pub fn descriptors_needed(cfg: &Config) -> u64 {
    let places = (cfg.api.max_clients + cfg.api.control_clients) as u64;
    let transports = if cfg.http.enabled { 2 } else { 1 };
    places * transports + OWN_DESCRIPTORS
}

/// Raise the soft limit of open files to the hard one (the default soft 1024 is a
/// limit for `select()`, which edod does not use), and refuse to start when even that
/// cannot hold the connection budget: edod then refuses connections beyond its places
/// before it runs out of descriptors, so `edoctl estop` always gets one. Returns the
/// limit.
pub fn raise_open_files(cfg: &Config) -> Result<u64> {
    use nix::sys::resource::{getrlimit, setrlimit, Resource};
    let (soft, hard) = getrlimit(Resource::RLIMIT_NOFILE).context("getrlimit(RLIMIT_NOFILE)")?;
    let limit = if soft < hard {
        match setrlimit(Resource::RLIMIT_NOFILE, hard, hard) {
            Ok(()) => hard,
            Err(e) => {
                tracing::warn!(soft, hard, error = %e, "cannot raise the open-file limit");
                soft
            }
        }
    } else {
        soft
    };
    let need = descriptors_needed(cfg);
    if limit < need {
        bail!(
            "api.max_clients = {} and api.control_clients = {} need {need} open files \
             ({} client places{}, and {OWN_DESCRIPTORS} of edod's own), but edod may open \
             only {limit} (its hard limit: `ulimit -Hn`, LimitNOFILE= in the unit); lower \
             api.max_clients or raise the limit",
            cfg.api.max_clients,
            cfg.api.control_clients,
            cfg.api.max_clients + cfg.api.control_clients,
            if cfg.http.enabled {
                " on the socket and as many on the dashboard"
            } else {
                " on the socket"
            },
        );
    }
    Ok(limit)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(dir: &Path, socket: &str) -> Config {
        let text = format!(
            "[api]\nsocket = {:?}\n[state]\ndir = {:?}\n",
            dir.join(socket).display().to_string(),
            dir.join("state").display().to_string()
        );
        Config::from_toml(&text, "t.toml").unwrap()
    }

    #[test]
    fn a_second_lock_on_the_state_dir_or_the_socket_names_the_holder() {
        let dir = tempfile::tempdir().unwrap();
        let first = lock(&config(dir.path(), "a.sock")).unwrap();
        let pid = format!("pid {}", std::process::id());
        for socket in ["a.sock", "b.sock"] {
            let e = lock(&config(dir.path(), socket)).unwrap_err().to_string();
            assert!(e.contains(&pid) && e.contains("a.sock"), "{e}");
            assert!(e.contains("state directory"), "{e}");
        }
        // Another state dir, the same socket.
        let other = tempfile::tempdir().unwrap();
        let mut cfg = config(other.path(), "x.sock");
        cfg.api.socket = dir.path().join("a.sock");
        let e = lock(&cfg).unwrap_err().to_string();
        assert!(e.contains(&pid) && e.contains("with this socket"), "{e}");
        drop(first);
        let again = lock(&config(dir.path(), "b.sock")).unwrap();
        let mode = std::fs::metadata(dir.path().join("state").join(STATE_LOCK_FILE))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, LOCK_FILE_MODE);
        drop(again);
    }

    #[test]
    fn links_and_open_directories_in_edods_state_are_refused_naming_them() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim");
        std::fs::write(&victim, "precious").unwrap();
        std::fs::set_permissions(&victim, std::fs::Permissions::from_mode(0o644)).unwrap();
        let state = dir.path().join("state");
        std::fs::create_dir(&state).unwrap();
        std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o750)).unwrap();
        let cfg = config(dir.path(), "a.sock");
        // A link at edod.lock, at <socket>.lock, at edod.db and at its -wal.
        let planted = [
            state.join(STATE_LOCK_FILE),
            socket_lock_path(&cfg.api.socket),
            state.join(DB_FILE),
            state.join(format!("{DB_FILE}-wal")),
        ];
        for link in &planted {
            std::os::unix::fs::symlink(&victim, link).unwrap();
            let e = lock(&cfg)
                .and_then(|l| secure_db_files(&state).map(|()| l))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("symbolic link") && e.contains(&link.display().to_string()),
                "{e}"
            );
            std::fs::remove_file(link).unwrap();
        }
        // The target was never written, truncated or chmod-ed.
        assert_eq!(std::fs::read_to_string(&victim).unwrap(), "precious");
        let mode = std::fs::metadata(&victim).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o644);
        // A state dir or socket dir others can write in.
        std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o777)).unwrap();
        let e = lock(&cfg).unwrap_err().to_string();
        assert!(e.contains("state dir") && e.contains("0777"), "{e}");
        std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o750)).unwrap();
        let open = dir.path().join("open");
        std::fs::create_dir(&open).unwrap();
        std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o1777)).unwrap();
        let mut cfg = cfg;
        cfg.api.socket = open.join("a.sock");
        let e = lock(&cfg).unwrap_err().to_string();
        assert!(
            e.contains("socket's directory") && e.contains("1777"),
            "{e}"
        );
    }
}
