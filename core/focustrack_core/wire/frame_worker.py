"""The shell of a service that reads the frames of z-stacks as they are published (the focus
and phase services): a subscription, a bounded queue, a worker thread and an expiry thread.

Every frame sample (``focustrack/v1/zframe/**``) waits in a bounded FIFO (`QUEUE_FRAMES`), so
a burst holds the publisher back instead of piling up without bound (Zenoh's callbacks
queue without limit); one thread takes the samples in order and hands each to the
service's `take`; another calls its `expire` every `expire_period_s`, since frames stop
coming when a peer stops sending and their expiry cannot wait for the next. The two never
run at the same time (one lock). What `take` returns, unless None, goes to `publish`,
outside the lock. `FrameReaderSettings` are the options such a service shares: its keys
and what peers' frames may make it hold; `WorkerBus` its session, opened in the
background, and the worker made on it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Generic, Protocol, TypeVar

import zenoh
from pydantic import Field

from focustrack_core.wire import codec, keys
from focustrack_core.wire.session import ATTEMPT_TIMEOUT_S, BackgroundSession, ZenohSettings
from focustrack_core.wire.trust import FrameSigner, ResultSigner, frame_signer_of, signer_of

log = logging.getLogger(__name__)

#: Every frame of every stack.
ZFRAME_SUBSCRIPTION = f"{keys.PREFIX}/zframe/**"
#: Frame samples waiting for the worker before the publisher is held back.
QUEUE_FRAMES = 64

T = TypeVar("T")
W = TypeVar("W", bound="Closable")

#: `take(key, payload, attachment)` of a sample: the payload still in Zenoh (copy it out
#: with `codec.payload_bytes` where it is read), the attachment's bytes (None: none).
Take = Callable[[str, zenoh.ZBytes, bytes | None], T | None]


class FrameWorker(Generic[T]):
    """Frame samples of `session` (those on `subscription`, a key expression: every frame by
    default) to `take` on a thread of its own (module docstring); `name` names the threads.
    A ValueError from `take` (the key names no tile: nowhere to answer) is logged and the
    sample skipped. With `alive_key`, a liveliness token is declared there once the
    subscription is (`keys.alive_key`): while it lives, frames reach this worker."""

    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        take: Take[T],
        publish: Callable[[T], None],
        expire: Callable[[], None],
        expire_period_s: float,
        subscription: str = ZFRAME_SUBSCRIPTION,
        alive_key: str | None = None,
    ) -> None:
        self._take = take
        self._publish = publish
        self._expire_stale = expire
        self._expire_period_s = expire_period_s
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._subscriber = session.declare_subscriber(
            subscription, zenoh.handlers.FifoChannel(QUEUE_FRAMES)
        )
        try:  # declared once the subscription is: frames reach this worker from then on
            self._token = (
                None if alive_key is None else session.liveliness().declare_token(alive_key)
            )
        except BaseException:
            self._subscriber.undeclare()
            raise
        self._thread = threading.Thread(target=self._serve, name=f"{name}-zenoh", daemon=True)
        self._thread.start()
        self._expiry = threading.Thread(target=self._expire, name=f"{name}-expiry", daemon=True)
        self._expiry.start()

    def _expire(self) -> None:
        while not self._closed.wait(self._expire_period_s):
            with self._lock:
                self._expire_stale()

    def _serve(self) -> None:
        for sample in self._subscriber:  # ends when the subscriber is undeclared
            key = str(sample.key_expr)
            attachment = None if sample.attachment is None else sample.attachment.to_bytes()
            try:
                with self._lock:
                    done = self._take(key, sample.payload, attachment)
            except ValueError as error:  # a key that names no tile: nowhere to answer
                log.warning("ignored sample on %s: %s", key, error)
                continue
            except Exception:  # a defect of ours: logged whole, and the thread goes on
                log.exception("sample on %s failed", key)
                continue
            if done is not None:
                self._publish(done)

    def close(self, timeout_s: float = 5.0) -> None:
        """Undeclare the token and the subscription, and end both threads (once: closing
        again does nothing)."""
        if self._closed.is_set():
            return
        if self._token is not None:
            self._token.undeclare()
        self._subscriber.undeclare()
        self._closed.set()
        self._thread.join(timeout_s)
        self._expiry.join(timeout_s)


class FrameReaderSettings(ZenohSettings):
    """The options of a service that reads frames and publishes results (focus, phase)."""

    result_key_file: Path | None = Field(
        None,
        description="shared key: tag every result with its HMAC, for the scheduler to check "
        "(docs/security.md)",
    )
    frame_key_file: Path | None = Field(
        None,
        description="the instrument's frame key: read only frames tagged with it, drop and "
        "count the others (docs/security.md)",
    )
    open_frames_mb: float = Field(
        codec.OPEN_FRAMES_BYTES / 1_000_000,
        gt=0,
        description="frames of stacks under way held at most, MB (frames in parts and what "
        "open stacks keep); a frame beyond it is refused and its stack answered with an error",
    )
    open_frame_timeout_s: float = Field(
        codec.OPEN_FRAME_TIMEOUT_S,
        gt=0,
        description="seconds a stack under way waits for its next frame (and a frame for "
        "its next part) before it is dropped",
    )

    @property
    def open_frames_bytes(self) -> int:
        """--open-frames-mb in bytes."""
        return int(self.open_frames_mb * 1_000_000)

    def signers(self) -> tuple[ResultSigner | None, FrameSigner | None]:
        """The result and frame keys read from their files (None: no file). A bad Zenoh
        option or config file, or a bad key file, is a ValueError here, not later."""
        self.zenoh()
        return signer_of(self.result_key_file), frame_signer_of(self.frame_key_file)


class Closable(Protocol):
    def close(self) -> None: ...


class WorkerBus(Generic[W]):
    """A frame reader's Zenoh session, opened in the background and tried again until the
    router answers (`BackgroundSession`), and the worker `make_worker` builds on it when it
    opens. `health` is the session's; `close` closes the workers, then the session."""

    def __init__(self, settings: ZenohSettings, make_worker: Callable[[zenoh.Session], W]) -> None:
        self.workers: list[W] = []
        self._session = BackgroundSession(
            lambda: settings.zenoh(ATTEMPT_TIMEOUT_S),
            lambda session: self.workers.append(make_worker(session)),
        )
        self.health = self._session.health

    def close(self) -> None:
        for worker in self.workers:
            worker.close()
        self._session.close()
