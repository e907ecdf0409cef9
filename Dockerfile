# Placeholder until the deploy issue: the image will install through scripts/setup-venv.sh
# and constraints.txt, exactly like the README's commands.
FROM python:3.11-slim
