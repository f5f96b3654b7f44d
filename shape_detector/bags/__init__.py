"""Bags: the CRC-checked MCAP writer, the output bag, output-path safety, damaged-chunk
reading and the replay command's argument checks and run loop.

The older reader (``open_bag``, ``BagFrameReader``) still lives in
:mod:`shape_detector.bag_io`; new bag code goes here, one job per module.
"""
