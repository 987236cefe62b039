"""Shared foundations of every product: the :class:`~.scan.Scan`, the error types, progress and
cancellation, atomic writes and output transactions, rigid transforms and the parameter base."""
