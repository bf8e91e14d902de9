"""Falconry services: each folder is one service (pure `core` + thin Zenoh `node`);
`runtime` holds the code they share and `launcher` the `falconry` command."""
