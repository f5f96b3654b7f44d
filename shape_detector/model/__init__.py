"""shape_detector.model"""
