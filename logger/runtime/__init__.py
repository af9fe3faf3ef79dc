"""The daemon at run time: sampler threads, sensor adapters, the navigator thread, the status socket, the
service manager and the journal."""
