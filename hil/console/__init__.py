"""The operator console (`hil serve`): a web page that starts a procedure on the engine `hil run` uses, shows
it live, takes the operator's answers and keeps every campaign of a folder at hand."""
