"""The aligner's bound on memory: decoded pixels and heavy requests in flight."""

from __future__ import annotations

import asyncio
import contextlib

from fleetmap.errors import PayloadTooLarge, Unavailable


class PixelBudget:
    """Decoded image pixels in flight in this process. A request holds its share while its
    images are decoded and aligned; others wait for room, up to `wait_s`, then get 503 with
    Retry-After. One request over the whole budget is refused with 413."""

    def __init__(self, capacity: int, wait_s: float = 30.0, requests: int = 2):
        self.capacity, self.wait_s, self.used = capacity, wait_s, 0
        self._cond = asyncio.Condition()
        self._slots = asyncio.Semaphore(requests)

    @contextlib.asynccontextmanager
    async def slot(self):
        """One of `requests` places for a heavy request, taken before its body is read
        (so waiting requests hold no memory); up to `wait_s`, then 503 with Retry-After."""
        try:
            await asyncio.wait_for(self._slots.acquire(), self.wait_s)
        except TimeoutError as exc:
            raise Unavailable(
                "The aligner is busy with other requests; try again", retry_after=10
            ) from exc
        try:
            yield
        finally:
            self._slots.release()

    @contextlib.asynccontextmanager
    async def hold(self, pixels: int):
        if pixels > self.capacity:
            raise PayloadTooLarge(
                f"{pixels} pixels in one request exceed the {self.capacity}-pixel budget: "
                "send fewer or smaller views"
            )
        async with self._cond:
            try:
                await asyncio.wait_for(
                    self._cond.wait_for(lambda: self.used + pixels <= self.capacity), self.wait_s
                )
            except TimeoutError as exc:
                raise Unavailable(
                    "The aligner is busy with other requests' images; try again",
                    retry_after=10,
                ) from exc
            self.used += pixels
        try:
            yield
        finally:
            async with self._cond:
                self.used -= pixels
                self._cond.notify_all()
