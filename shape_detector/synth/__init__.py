"""shape_detector.synth"""
