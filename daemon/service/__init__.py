"""The asyncio service (``mocapd run``): the only place besides the transports that imports asyncio."""
