"""Zero-copy intra-process messaging between the nodes of one container.

The component API is in :mod:`container.intra.api` (re-exported here); the
container-owned state (the bus, each subscription's queue, the loan pool)
in :mod:`.bus`, :mod:`.queue` and :mod:`.pool`; the DDS side of an
intra-process subscription in :mod:`.dds_reader`. Rules for users:
container/intra/README.md.
"""

from .api import LoanedMessage, Publisher, Subscription, create_publisher, create_subscription
from .bus import get_bus
from .pool import Loan

__all__ = ["get_bus", "Loan", "LoanedMessage", "Publisher", "Subscription", "create_publisher", "create_subscription"]
