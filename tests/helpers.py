"""Small helpers shared by the tests."""
from __future__ import annotations


def interrupt_at(update: int):
    """An ``on_chunk`` callback that simulates Ctrl-C once chunk ``update`` has been saved."""
    def on_chunk(done: int) -> None:
        if done == update:
            raise KeyboardInterrupt

    return on_chunk
