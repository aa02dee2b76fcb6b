"""
ROS domain ids reserved on this host, so that test suites running side by side never share one.

Holding domain id d means holding the Linux abstract Unix socket named NAMESPACE-d (no file on
disk): the kernel lets one socket at a time bind a name, so two holders of one id cannot exist
on this host (in one network namespace, which is also as far as LOCALHOST discovery reaches),
and it frees the name when its holder closes the socket or exits, however it exits.  The socket
is not inherited by subprocesses (PEP 446): a test process holds the ids of the processes it
starts, and passes them on in ROS_DOMAIN_ID.
"""

import errno
import os
import random
import socket

NAMESPACE = 'quatcal_ros-test-domain'


def _users_domain(environ=os.environ):
    """Return the ROS_DOMAIN_ID the suite started with (the user's own graph), or 0."""
    value = environ.get('ROS_DOMAIN_ID', '').strip()
    return int(value) if value.isdigit() else 0


# Ids whose ports (Fast DDS: 7400 + 250 * id + ...) stay below Linux's ephemeral range with
# LOCALHOST discovery are 0-101.  Left out: 0, everyone's default domain, the user's own
# ROS_DOMAIN_ID (a robot's graph holds no reservation), and 68, the fixed default of
# bench/bench_node.py (bench/bench_soak.py reserves its id here).
DOMAIN_IDS = tuple(d for d in range(102) if d not in (0, 68, _users_domain()))


class DomainsExhausted(RuntimeError):
    """Every candidate domain id is held by another holder on this host."""


class Reservation:
    """A domain id held until release() (or the end of a `with` block, or of the process)."""

    def __init__(self, domain_id, held_socket):
        self.domain_id = domain_id
        self._socket = held_socket

    @property
    def held(self):
        """Tell whether the id is still held: from reserve() until it is released."""
        return self._socket is not None

    def release(self):
        """Let another holder reserve this id (a second call does nothing)."""
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.release()

    def __repr__(self):
        state = 'held' if self.held else 'released'
        return f'Reservation(domain_id={self.domain_id}, {state})'


def socket_name(domain_id, namespace=NAMESPACE):
    """Return the abstract socket address that stands for `domain_id` (leading NUL byte)."""
    return f'\0{namespace}-{domain_id}'


def reserve(candidates=DOMAIN_IDS, namespace=NAMESPACE):
    """
    Reserve a domain id of `candidates` that no one else on this host holds; a Reservation.

    The candidates are tried in random order, so that suites started together do not race for
    the same ids and an id just released is not always the next one handed out.  Raises
    DomainsExhausted when every candidate is held.
    """
    order = list(candidates)
    random.shuffle(order)
    for domain_id in order:
        held = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            held.bind(socket_name(domain_id, namespace))
        except OSError as error:
            held.close()
            if error.errno == errno.EADDRINUSE:
                continue
            raise
        return Reservation(domain_id, held)
    raise DomainsExhausted(
        f'all {len(order)} candidate ROS domain ids are held on this host (abstract sockets '
        f'@{namespace}-<id>): other test runs are using them; wait for one to end')
