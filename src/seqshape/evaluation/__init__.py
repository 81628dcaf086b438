"""seqshape.evaluation"""
