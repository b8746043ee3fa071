//! The machine's end of the cable, shared by both protocol ends: a pseudo-terminal
//! throttled to the baud rate, which can be unplugged and plugged in again.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{ErrorKind, Read, Write};
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use crate::sim::{after_ms, Summary};

/// The machine's end of the cable: a pty (behind the `--link` symlink when one is
/// asked for) throttled to the baud rate both ways, which can be unplugged (closed: the
/// host sees a hang-up, the symlink goes) and plugged in again as a new pty behind the
/// same symlink. Both protocol ends (edo and `--gcode`) use it.
pub(crate) struct PtyPort {
    link: Option<PathBuf>,
    /// `None` while unplugged.
    pty: Option<Pty>,
    replug_at: Option<u64>,
    /// Wall time one byte takes on the line, µs.
    byte_us: f64,
    /// Bytes the line may carry now, each way.
    rx_credit: f64,
    tx_credit: f64,
    /// Most line credit banked while idle, bytes.
    bank_bytes: f64,
}

impl PtyPort {
    /// A fresh pty at `baud` banking at most `bank_bytes` of line credit, and the path
    /// the host should open.
    pub(crate) fn open(
        link: Option<&Path>,
        baud: u32,
        bank_bytes: f64,
    ) -> anyhow::Result<(Self, PathBuf)> {
        let pty = open_pty(link)?;
        let ready = link.map_or_else(|| pty.slave_path.clone(), Path::to_path_buf);
        let port = PtyPort {
            link: link.map(Path::to_path_buf),
            pty: Some(pty),
            replug_at: None,
            byte_us: 10_000_000.0 / f64::from(baud.max(1)),
            rx_credit: 0.0,
            tx_credit: 0.0,
            bank_bytes,
        };
        Ok((port, ready))
    }

    /// Pull the cable (at `now_us`, for `for_ms`): the pty closes, master and slave, so
    /// the host sees a hang-up, and the symlink goes. False if it was already unplugged.
    pub(crate) fn unplug(&mut self, now_us: u64, for_ms: u64) -> bool {
        if self.pty.take().is_none() {
            return false;
        }
        self.remove_link();
        self.replug_at = Some(after_ms(now_us, for_ms));
        true
    }

    /// Plug a new pty in behind the same symlink once the unplug is over.
    pub(crate) fn replug_if_due(&mut self, now_us: u64) -> anyhow::Result<()> {
        if self.replug_at.is_some_and(|at| now_us >= at) {
            self.pty = Some(open_pty(self.link.as_deref())?);
            self.replug_at = None;
        }
        Ok(())
    }

    /// Remove the symlink (the simulator stops, or the cable is pulled).
    pub(crate) fn remove_link(&self) {
        if let Some(l) = &self.link {
            let _ = std::fs::remove_file(l);
        }
    }

    /// Host -> machine, throttled to the line: `dt_us` of line time is credited (at most
    /// the bank) and up to the credit is read into `buf`. Returns how many bytes
    /// were read: 0 when stalled, unplugged, or nothing came (a hang-up, EIO, is not an
    /// error: the host may reopen).
    pub(crate) fn read(
        &mut self,
        buf: &mut [u8],
        dt_us: u64,
        stalled: bool,
        sum: &mut Summary,
    ) -> anyhow::Result<usize> {
        let new = dt_us as f64 / self.byte_us;
        self.rx_credit = (self.rx_credit + new).min(self.bank_bytes.max(new));
        let want = (self.rx_credit as usize).min(buf.len());
        let Some(p) = self.pty.as_mut() else {
            return Ok(0);
        };
        if want == 0 || stalled {
            return Ok(0);
        }
        match p.master.read(&mut buf[..want]) {
            Ok(n) => {
                self.rx_credit -= n as f64;
                sum.bytes_from_host += n as u64;
                Ok(n)
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(0),
            Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => Ok(0),
            Err(e) => Err(e).context("read from the pty"),
        }
    }

    /// Machine -> host through the pty, throttled the same way: writes what the credit
    /// allows from the front of `tx`; unplugged, `tx` is dropped (nobody listens).
    pub(crate) fn write(
        &mut self,
        tx: &mut VecDeque<u8>,
        dt_us: u64,
        sum: &mut Summary,
    ) -> anyhow::Result<()> {
        let new = dt_us as f64 / self.byte_us;
        self.tx_credit = (self.tx_credit + new).min(self.bank_bytes.max(new));
        let Some(p) = self.pty.as_mut() else {
            tx.clear();
            return Ok(());
        };
        let n = (self.tx_credit as usize).min(tx.len());
        if n == 0 {
            return Ok(());
        }
        let chunk: Vec<u8> = tx.iter().take(n).copied().collect();
        match p.master.write(&chunk) {
            Ok(w) => {
                tx.drain(..w);
                self.tx_credit -= w as f64;
                sum.bytes_to_host += w as u64;
                Ok(())
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(()),
            Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => Ok(()),
            Err(e) => Err(e).context("write to the pty"),
        }
    }
}

struct Pty {
    master: File,
    _slave: OwnedFd,
    slave_path: PathBuf,
}

/// A pty whose two ends are close-on-exec from the start. Neither end may leak into a
/// process spawned meanwhile by another thread (a test's edod): an inherited master keeps
/// the pty alive, so an unplug would not hang up the host, and an inherited end holds
/// the tty past the simulator's own close. `openpty` and a later `FD_CLOEXEC` leave a
/// window for that; `posix_openpt(O_CLOEXEC)` and an `O_CLOEXEC` open of the slave do not.
fn open_pty_cloexec() -> anyhow::Result<nix::pty::OpenptyResult> {
    use nix::fcntl::{open, OFlag};
    use nix::pty::{grantpt, posix_openpt, ptsname_r, unlockpt};
    use std::os::fd::{FromRawFd, IntoRawFd, OwnedFd};
    let master =
        posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC).context("posix_openpt")?;
    grantpt(&master).context("grantpt")?;
    unlockpt(&master).context("unlockpt")?;
    let name = ptsname_r(&master).context("ptsname")?;
    let slave = open(
        name.as_str(),
        OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC,
        nix::sys::stat::Mode::empty(),
    )
    .with_context(|| format!("open {name}"))?;
    // SAFETY: `into_raw_fd` gives up the only owner of the master's descriptor.
    let master = unsafe { OwnedFd::from_raw_fd(master.into_raw_fd()) };
    Ok(nix::pty::OpenptyResult { master, slave })
}

fn open_pty(link: Option<&Path>) -> anyhow::Result<Pty> {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
    use std::os::fd::AsRawFd;
    let pty = open_pty_cloexec()?;
    let mut t = tcgetattr(&pty.slave).context("tcgetattr on the pty")?;
    cfmakeraw(&mut t);
    tcsetattr(&pty.slave, SetArg::TCSANOW, &t).context("tcsetattr raw on the pty")?;
    let flags = fcntl(&pty.master, FcntlArg::F_GETFL).context("fcntl F_GETFL")?;
    fcntl(
        &pty.master,
        FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
    )
    .context("fcntl O_NONBLOCK")?;
    let slave_path = std::fs::read_link(format!("/proc/self/fd/{}", pty.slave.as_raw_fd()))
        .context("find the pty's path")?;
    if let Some(link) = link {
        match std::fs::symlink_metadata(link) {
            Ok(m) if m.file_type().is_symlink() => std::fs::remove_file(link)
                .with_context(|| format!("replace old symlink {}", link.display()))?,
            Ok(_) => bail!(
                "{} exists and is not a symlink: refusing to replace it",
                link.display()
            ),
            Err(_) => {}
        }
        std::os::unix::fs::symlink(&slave_path, link)
            .with_context(|| format!("symlink {} -> {}", link.display(), slave_path.display()))?;
    }
    Ok(Pty {
        master: File::from(pty.master),
        _slave: pty.slave,
        slave_path,
    })
}
