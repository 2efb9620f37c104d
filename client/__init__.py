"""The haptic client: the 1 kHz local-model servo loop (render, safety, scheduler), the devices,
the session and the network link to the server."""
