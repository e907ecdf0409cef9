"""The central learner and what hosts it: its process and Ray shell, device, counters, checkpoint
files and ONNX export."""
