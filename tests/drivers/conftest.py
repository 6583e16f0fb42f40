"""Driver tests share the link tests' leak check (threads of observers, notifiers, peers)."""

from tests.link.conftest import no_leaked_threads  # noqa: F401
