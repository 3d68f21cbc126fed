"""Cluster mode: workers on NATS share the streams' partitions.

:mod:`daemon.cluster.ring` says which live member owns which partition (rendezvous hashing, pure);
:mod:`daemon.cluster.membership` keeps the live members in etcd (leases, a watch) and the statuses
the workers report. Nothing is imported here, so the pure ring loads neither asyncio nor etcd's
client.
"""
