"""seqshape.train"""
