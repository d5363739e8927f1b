"""Learned state-based chunk policies: demonstration collection, dataset I/O, models and training.

Everything here runs on the CPU without ROS; torch is imported only by the modules that need it.
"""
