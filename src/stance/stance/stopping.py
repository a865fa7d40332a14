"""Cooperative stops: a long computation of the library (a plan's verification,
interpolation, time-optimal timing) asks its caller's should_stop() between units of work
and abandons on True, so that a node shutting down never waits for it to end."""


class Stopped(Exception):
    """should_stop() answered True: the computation was abandoned (the message says where)."""


def stop_if_asked(should_stop, where: str) -> None:
    """Raise Stopped(where) when should_stop (a callable; None: never) answers True."""
    if should_stop is not None and should_stop():
        raise Stopped(where)
