"""What formtwin's own asyncua servers share (the simulated press, the estimates' server):
an event loop in a thread of its own, and a server with the line's security settings."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Coroutine
from typing import Any


class LoopThread:
    """An asyncio event loop running in a daemon thread named ``name``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the loop's thread (once)."""
        if self.loop is None:
            self.loop = asyncio.new_event_loop()
            self._thread = threading.Thread(target=self.loop.run_forever, daemon=True,
                                            name=self.name)
            self._thread.start()

    def call(self, coro: Coroutine[Any, Any, Any], timeout: float = 30.0) -> Any:
        """Run ``coro`` on the loop; wait for and return its result."""
        assert self.loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def post(self, fn: Callable[..., Any], *args: Any) -> None:
        """Call ``fn(*args)`` on the loop, without waiting."""
        assert self.loop is not None
        self.loop.call_soon_threadsafe(fn, *args)

    def close(self) -> None:
        """Cancel the loop's leftover tasks (a server's session timeouts), stop the loop and
        its thread."""
        if self.loop is None:
            return
        self.call(_cancel_pending())
        self.loop.call_soon_threadsafe(self.loop.stop)
        if self._thread is not None:
            self._thread.join(10.0)
        self.loop.close()
        self.loop = None


async def _cancel_pending() -> None:
    tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


async def make_server(url: str, name: str, certificate: tuple[str, str] | None = None,
                      users: dict[str, str] | None = None) -> Any:
    """An initialised asyncua server at ``url`` named ``name`` (not started): with
    ``certificate`` (certificate and private key files) Basic256Sha256 SignAndEncrypt
    sessions only, else security mode None; with ``users`` (name -> password) only these
    users, else anonymous clients."""
    from asyncua import ua
    from asyncua.server.server import Server

    server = Server(user_manager=None if users is None else user_manager(users))
    await server.init()
    server.set_endpoint(url)
    server.set_server_name(name)
    if certificate is None:
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    else:
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        await server.load_certificate(certificate[0])
        await server.load_private_key(certificate[1])
    server.set_identity_tokens([ua.AnonymousIdentityToken] if users is None
                               else [ua.UserNameIdentityToken])
    return server


def user_manager(users: dict[str, str]) -> Any:
    """An asyncua user manager accepting the user name -> password pairs ``users`` only."""
    from asyncua.crypto.permission_rules import User, UserRole
    from asyncua.server.user_managers import UserManager

    class Users(UserManager):
        def get_user(self, iserver: Any, username: str | None = None,
                     password: str | None = None, certificate: Any = None) -> User | None:
            ok = username is not None and users.get(username) == password
            return User(role=UserRole.User) if ok else None

    return Users()


__all__ = ["LoopThread", "make_server", "user_manager"]
