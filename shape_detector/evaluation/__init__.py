"""shape_detector.evaluation"""
