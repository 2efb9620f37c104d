"""The authoritative server: the global deformable object, every user's contact, the sans-I/O room
and its asyncio layer, the viewer stream and the benchmarks run on the server side."""
