"""Code the server and the client share, with no I/O: the local model, the stability analysis,
the gain design, the protocol and the rates (sockets, threads and clocks stay outside; time is
passed in). See the README's Layout for each module."""
