"""shape_detector.proposals"""
