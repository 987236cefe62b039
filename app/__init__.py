"""The use cases of forestreg, one file each: what every front door (command line, desktop, job
service, batch) calls.

=====================  ==========================================================
``change``             two surveys of one plot compared tree by tree (``change``)
=====================  ==========================================================
"""
