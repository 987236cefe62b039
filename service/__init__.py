"""The forestreg job service and the batch engine (``forestreg serve``, ``forestreg batch``).

- :mod:`.store`: the job store, an SQLite database that survives restarts (also ``kill -9``).
- :mod:`.jobs`: runs each job as a ``forestreg`` CLI process (its own process group) and reads its
  JSON-lines progress events.
- :mod:`.app`: the HTTP/JSON API (FastAPI on uvicorn), token-protected.
- :mod:`.batch`: many plots at once on Dask distributed (a local cluster or a scheduler address).

Nothing here is imported by ``import forestreg``; FastAPI and Dask load only when a service or a
batch starts.
"""
