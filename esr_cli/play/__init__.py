"""`esr play`: a person in the human's seat with a trained robot, in a terminal or a browser.

game.py     the one game loop (keys -> human actions, the robot's policy, the episode's end)
session.py  the session (counterbalanced robots, neutral labels) and its `play` artifacts
study.py    a user study's file; pages.py its pages and the checks of the answers;
study_session.py  its flow (consent, instructions, practice, blocks, questionnaires, the end)
terminal.py the terminal front end; web.py the browser front end (docs/play.md)
"""
