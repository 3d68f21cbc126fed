"""Cluster mode: workers on NATS share the streams' partitions.

:mod:`daemon.cluster.ring` says which live member owns which partition (rendezvous hashing, pure).
The adapters that talk to servers are the service's: :mod:`daemon.service.membership` keeps the
live members in etcd (leases, a watch) and the statuses the workers report. Nothing is imported
here.
"""
