"""shape_detector.training"""
