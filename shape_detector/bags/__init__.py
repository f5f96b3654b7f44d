"""Bags: reading (source, topics, reader, damaged-MCAP recovery, ROS 1 conversion), the output
bag (CRC-checked MCAP writer, output-path safety), and the replay (offline loop, player, CLI
checks, detector factory, scene recording). One job per module."""
